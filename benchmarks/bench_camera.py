"""What knowing the camera could buy the 3D answer: the oracle table of issue "3D you can trust".

For each set (`paper-clean`, noisy and occluded `paper`, `street`) and shape class, on the first
--samples masks of bench_accuracy's seeded 256 px validation spools, two rows:

* **lift**: the true corners plus Gaussian noise of 0.5, 1 and 2 px, lifted to a cuboid
  (`lift.lift`), the camera free and given (the true focal length and principal point, held:
  `intrinsics.KnownCamera`): how much the camera fixes when the corners are good;
* **mask fit**: the cuboid fitted to the noisy mask from the shipped networks' corners, the
  mask's own shape class (`Fitter.fit_cuboids`, as `infer` fits it), free and given.

Each with the median relative error of depth/height (every part), the median 3D IoU up to
scale, the median yaw error, and for the mask fit the median corner error on the true outline
(hull) and of the interior corners.

    .venv/bin/python benchmarks/bench_camera.py --samples 40 --json bench-camera.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import spool_for  # noqa: E402
from cuboidtrain.fit.cuboid import fit_candidates  # noqa: E402
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.masks import frame, silhouette  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.geometry.intrinsics import KnownCamera  # noqa: E402
from cuboidtrain.geometry.lift import lift  # noqa: E402
from cuboidtrain.geometry.scoring import Truth, score  # noqa: E402
from shared.sample import decode  # noqa: E402
from shared.spool import enumerate_spool, read_sample_bytes  # noqa: E402

SETS = [(scene, shape) for scene in ("paper-clean", "paper", "street") for shape in ("box", "twobox")]
NOISE_PX = (0.5, 1.0, 2.0)
FRAME = 256  # px: the spools' masks
CAMERAS = ("free", "plausible", "given")  # fitted unbounded, fitted within plausible bounds, given


def true_camera(truth: Truth) -> KnownCamera:
    """The focal length and principal point the generator framed the sample with, in its px."""
    vector = truth.camera.vector
    return KnownCamera(float(np.exp(vector[7]) / vector[8]), (float(vector[9]), float(vector[10])))


def figures(scored: list) -> dict:
    """Medians over the scored fits (`scoring.CornerErrors`); None where none answered."""
    answered = [s for s in scored if s is not None]
    if not answered:
        return {"answered": 0}
    return {"answered": len(answered), "samples": len(scored),
            "depth_height_median_rel": float(np.median(np.concatenate([s.depth_height for s in answered]))),
            "iou3d_median": float(np.nanmedian([s.iou3d for s in answered])),
            "yaw_median_deg": float(np.nanmedian([s.yaw_deg for s in answered])),
            "hull_median_px": float(np.median(np.concatenate([s.hull for s in answered]))),
            "interior_median_px": float(np.median(np.concatenate([s.interior for s in answered] + [np.zeros(0)])))
            if any(len(s.interior) for s in answered) else None}


def lift_rows(truths: list[Truth], rng: np.random.Generator) -> dict:
    rows = {}
    for sigma in NOISE_PX:
        noisy = [t.keypoints + rng.normal(0.0, sigma, t.keypoints.shape) for t in truths]
        for camera in CAMERAS:
            scored = []
            for truth, corners in zip(truths, noisy):
                known = true_camera(truth) if camera == "given" else None
                frame = None if camera == "free" else (FRAME, FRAME)
                lifted = lift(corners, truth.shape, known=known, frame=frame).camera
                scored.append(score(lifted.named_keypoints(), truth.shape.ratio_dict(lifted.ratios()), truth, lifted))
            rows[f"lift {sigma} px, {camera}"] = figures(scored)
    return rows


def mask_rows(fitter: Fitter, samples: list, truths: list[Truth], shape: str) -> dict:
    model = next(m for m in fitter.models if m.shape == shape)
    masks = [silhouette(s.noisy.astype(bool)) for s in samples]
    candidates = [fitter.fit_framed(model, *frame(m, model.size, fitter.options.margin)) for m in masks]
    rows = {}
    for camera in CAMERAS:
        known = [true_camera(t) if camera == "given" else None for t in truths]
        fitted = fit_candidates(candidates, masks, known=known, plausible=camera != "free")
        rows[f"mask fit, {camera}"] = figures([score(f.fit.keypoints, f.fit.ratios, t, f.fit.camera)
                                               if hasattr(f, "fit") else None for f, t in zip(fitted, truths)])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--seed", type=int, default=0, help="Of the corners' noise.")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    rng, result = np.random.default_rng(args.seed), {}
    for scene, shape in SETS:
        spool = spool_for(args.spools, shape, scene, args.samples)
        samples = [decode(read_sample_bytes(spool, n)) for n in enumerate_spool(spool)[: args.samples]]
        truths = [Truth.of_sample(s) for s in samples]
        result[f"{scene} {shape}"] = lift_rows(truths, rng) | mask_rows(fitter, samples, truths, shape)
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


def show(result: dict) -> None:
    table = Table(title="depth/height, 3D IoU and yaw, camera free and given (medians)")
    for column in ("set", "row", "d/h rel %", "3D IoU", "yaw deg", "hull px", "interior px"):
        table.add_column(column)
    for name, rows in result.items():
        for row, f in rows.items():
            if not f.get("answered"):
                table.add_row(name, row, "-", "-", "-", "-", "-")
                continue
            interior = "-" if f["interior_median_px"] is None else f"{f['interior_median_px']:.2f}"
            table.add_row(name, row, f"{100 * f['depth_height_median_rel']:.1f}", f"{f['iou3d_median']:.3f}",
                          f"{f['yaw_median_deg']:.1f}", f"{f['hull_median_px']:.2f}", interior)
    Console(width=140).print(table)


if __name__ == "__main__":
    main()
