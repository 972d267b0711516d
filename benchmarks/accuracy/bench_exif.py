"""What a photo's EXIF focal length buys the 3D answer (`infer --photo`, issue 38 Must have 6).

On the first --samples masks of bench_accuracy's seeded 256 px `street` spools (box and twobox),
`infer`'s answer (`Fitter.fit`: both shipped models, the cuboid fit, the choice) three ways: the
camera fitted (plausible, the default), the focal length from a photo's EXIF, and the true
camera given (held). Each mask's "photo" is a JPEG whose EXIF says the true focal length as a
35 mm equivalent rounded to whole mm, as cameras write it: each sample draws a lens of 24-70 mm
(equivalent), and the photo is the 4:3 frame whose diagonal makes the sample's focal length that
lens; the mask is a crop of it at its scale, so the principal point stays fitted
(`cuboidtrain.fit.exif`). The EXIF is read back from the file (`read_photo_camera`).

Medians of the relative depth/height error (every part), 3D IoU and yaw error, over the masks
given their own shape class, and the share of those. A fourth row, "exif, whole frame", is what a
mask of the photo's whole frame would get: the principal point at the photo's centre (for a
generated view, its true one), as loosely held.

    .venv/bin/python benchmarks/accuracy/bench_exif.py --samples 60 --json bench-exif.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import ExifTags, Image
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import spool_for  # noqa: E402
from bench_camera import figures  # noqa: E402
from cuboidtrain.fit.exif import FULL_FRAME_DIAGONAL_MM, read_photo_camera  # noqa: E402
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.geometry.accuracy import Truth, against_truth  # noqa: E402
from cuboidtrain.geometry.intrinsics import EXIF_PRINCIPAL_SIDES, KnownCamera  # noqa: E402
from shared.sample import decode  # noqa: E402
from shared.spool import enumerate_spool, read_sample_bytes  # noqa: E402

CAMERAS = ("fitted", "exif", "exif, whole frame", "given")
FRAME = 256  # px: the spools' masks
LENS_MM = (24.0, 70.0)  # 35 mm equivalent focal lengths drawn for the photos


def photo_for(truth: Truth, lens_mm: float, path: Path) -> Path:
    """A 4:3 JPEG whose diagonal makes the truth's focal length (px) a `lens_mm` lens (35 mm
    equivalent), its EXIF saying that lens rounded to whole mm."""
    diagonal = truth.known_camera().focal_px * FULL_FRAME_DIAGONAL_MM / lens_mm
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = round(lens_mm)
    Image.new("L", (round(0.8 * diagonal), round(0.6 * diagonal))).save(path, exif=exif)
    return path


def whole_frame(exif: KnownCamera, truth: Truth) -> KnownCamera:
    """What a mask of the photo's whole frame would get: the principal point at the frame's centre,
    which for a generated view is its true one, as loose a prior as EXIF's (`PhotoCamera.in_frame`)."""
    return replace(exif, principal_px=truth.known_camera().principal_px,
                   principal_stiffness=1 / (EXIF_PRINCIPAL_SIDES * FRAME), exif=("focal_px", "principal_px"))


def rows(fitter: Fitter, samples: list, truths: list[Truth], rng: np.random.Generator, folder: Path) -> dict:
    photos = [read_photo_camera(photo_for(t, rng.uniform(*LENS_MM), folder / f"{k}.jpg"))
              for k, t in enumerate(truths)]
    result = {}
    for camera in CAMERAS:
        fits = []
        for sample, truth, photo in zip(samples, truths, photos):
            mask = sample.noisy.astype(np.uint8) * 255
            known = {"fitted": None, "exif": photo.in_frame(mask.shape), "given": truth.known_camera(),
                     "exif, whole frame": whole_frame(photo.in_frame(mask.shape), truth)}[camera]
            fits.append(fitter.fit(mask, camera=known))
        right = [f.shape == t.shape.name for f, t in zip(fits, truths)]
        scored = [against_truth(f.keypoints, f.ratios, t, f.cuboid.fit.camera) if ok else None
                  for f, t, ok in zip(fits, truths, right)]
        result[camera] = figures(scored) | {"shape_right": float(np.mean(right))}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=60, help="Masks a shape class.")
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--seed", type=int, default=0, help="Of the photos' lenses.")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    rng, result = np.random.default_rng(args.seed), {}
    with tempfile.TemporaryDirectory(prefix="bench-exif-") as folder:
        for shape in ("box", "twobox"):
            spool = spool_for(args.spools, shape, "street", args.samples)
            samples = [decode(read_sample_bytes(spool, n)) for n in enumerate_spool(spool)[: args.samples]]
            result[f"street {shape}"] = rows(fitter, samples, [Truth.of_sample(s) for s in samples], rng, Path(folder))
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


def show(result: dict) -> None:
    table = Table(title="street masks: the camera fitted, from EXIF, given (medians)")
    for column in ("set", "camera", "d/h rel %", "3D IoU", "yaw deg", "shape %"):
        table.add_column(column)
    for name, by_camera in result.items():
        for camera, f in by_camera.items():
            table.add_row(name, camera, f"{100 * f['depth_height_median_rel']:.1f}", f"{f['iou3d_median']:.3f}",
                          f"{f['yaw_median_deg']:.1f}", f"{100 * f['shape_right']:.0f}")
    Console(width=120).print(table)


if __name__ == "__main__":
    main()
