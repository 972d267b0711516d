"""What knowing the camera could buy the 3D answer: the oracle table of issue "3D you can trust".

For each set (`paper-clean`, noisy and occluded `paper`, `street`) and shape class, on the first
--samples masks of bench_accuracy's seeded 256 px validation spools, two rows:

* **lift**: the true corners plus Gaussian noise of 0.5, 1 and 2 px, lifted to a cuboid
  (`lift.lift`), the camera free and given (the true focal length and principal point, held:
  `intrinsics.KnownCamera`): how much the camera fixes when the corners are good;
* **infer**: the answer `infer` gives for the noisy mask (`Fitter.fit`: both shipped models,
  their cuboids, the choice), the camera fitted unbounded (`plausible_camera=False`), fitted
  within plausible bounds (the default) and given.

Each with the median relative error of depth/height (every part), the median 3D IoU up to
scale, the median yaw error, the median corner error on the true outline (hull) and of the
interior corners, and for infer the share of masks given their own shape class (the figures
are those of these masks).

    .venv/bin/python benchmarks/accuracy/bench_camera.py --samples 40 --json bench-camera.json
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
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.geometry.lift import lift  # noqa: E402
from cuboidtrain.geometry.accuracy import Truth, against_truth, yaw_error_deg  # noqa: E402
from shared.sample import decode  # noqa: E402
from shared.spool import enumerate_spool, read_sample_bytes  # noqa: E402

SETS = [(scene, shape) for scene in ("paper-clean", "paper", "street") for shape in ("box", "twobox")]
NOISE_PX = (0.5, 1.0, 2.0)
FRAME = 256  # px: the spools' masks
CAMERAS = ("free", "plausible", "given")  # fitted unbounded, fitted within plausible bounds, given


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
                known = truth.known_camera() if camera == "given" else None
                frame = None if camera == "free" else (FRAME, FRAME)
                lifted = lift(corners, truth.shape, known=known, frame=frame).camera
                scored.append(against_truth(lifted.named_keypoints(), truth.shape.ratio_dict(lifted.ratios()), truth, lifted))
            rows[f"lift {sigma} px, {camera}"] = figures(scored)
    return rows


def infer_rows(fitters: dict[str, Fitter], samples: list, truths: list[Truth]) -> dict:
    """The answer `infer` gives (`Fitter.fit` on the noisy mask, both shape classes, the choice
    among them), the camera fitted unbounded, fitted within plausible bounds, and given."""
    rows = {}
    for camera, fitter in fitters.items():
        fits = [fitter.fit(s.noisy.astype(np.uint8) * 255, camera=t.known_camera() if camera == "given" else None)
                for s, t in zip(samples, truths)]
        right = [f.shape == t.shape.name for f, t in zip(fits, truths)]
        scored = [against_truth(f.keypoints, f.ratios, t, f.cuboid.fit.camera) if ok else None
                  for f, t, ok in zip(fits, truths, right)]
        rows[f"infer, {camera}"] = (figures(scored) | {"shape_right": float(np.mean(right))}
                                    | coverage([f for f, ok in zip(fits, right) if ok],
                                               [t for t, ok in zip(truths, right) if ok]))
    return rows


def coverage(fits: list, truths: list[Truth]) -> dict:
    """How often the truth lies within one and two of the fit's standard deviations: every ratio
    (each part's), the yaw, the focal length where fitted."""
    z = {"ratios": [], "yaw": [], "focal": []}
    for fit, truth in zip(fits, truths):
        spread = fit.cuboid.fit.spread
        if spread is None:
            continue
        fitted = truth.shape.ratio_vector(fit.ratios)
        z["ratios"] += list(np.abs(fitted - truth.shape.ratio_vector(truth.ratios)) / spread.ratios)
        z["yaw"].append(yaw_error_deg(fit.cuboid.fit.camera, truth.camera) / spread.yaw_deg)
        if spread.focal_px is not None:
            z["focal"].append(abs(fit.cuboid.fit.focal_px - truth.camera.focal_px()) / spread.focal_px)
    every = np.concatenate([np.asarray(v, dtype=float) for v in z.values()])
    return {f"within_{n}sd_{name}": float(np.mean(np.asarray(v) <= n)) if len(v) else None
            for name, v in (*z.items(), ("all", every)) for n in (1, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--seed", type=int, default=0, help="Of the corners' noise.")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitters = {camera: Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, plausible_camera=camera != "free"))
               for camera in CAMERAS}
    rng, result = np.random.default_rng(args.seed), {}
    for scene, shape in SETS:
        spool = spool_for(args.spools, shape, scene, args.samples)
        samples = [decode(read_sample_bytes(spool, n)) for n in enumerate_spool(spool)[: args.samples]]
        truths = [Truth.of_sample(s) for s in samples]
        result[f"{scene} {shape}"] = lift_rows(truths, rng) | infer_rows(fitters, samples, truths)
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


def show(result: dict) -> None:
    table = Table(title="depth/height, 3D IoU and yaw, camera free and given (medians)")
    for column in ("set", "row", "d/h rel %", "3D IoU", "yaw deg", "hull px", "interior px", "shape %",
                   "in 1 sd %", "in 2 sd %"):
        table.add_column(column)
    for name, rows in result.items():
        for row, f in rows.items():
            if not f.get("answered"):
                table.add_row(name, row, *["-"] * 8)
                continue
            interior = "-" if f["interior_median_px"] is None else f"{f['interior_median_px']:.2f}"
            shape = f"{100 * f['shape_right']:.0f}" if "shape_right" in f else ""
            within = [f"{100 * f[k]:.0f}" if f.get(k) is not None else "" for k in ("within_1sd_all", "within_2sd_all")]
            table.add_row(name, row, f"{100 * f['depth_height_median_rel']:.1f}", f"{f['iou3d_median']:.3f}",
                          f"{f['yaw_median_deg']:.1f}", f"{f['hull_median_px']:.2f}", interior, shape, *within)
    Console(width=140).print(table)


if __name__ == "__main__":
    main()
