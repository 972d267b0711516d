"""Choosing the mask-fit optimiser by measurement (issue 20, Must have 3): Levenberg-Marquardt on
contour distances (`cuboidtrain.geometry.mask_fit.fit_mask`, the `--cuboid` default) against a
soft-rasterised silhouette fitted by gradient descent through a blur schedule
(`cuboidtrain.geometry.soft_mask_fit.fit_soft`), from the same network candidate.

For each validation set (the seeded 256 px spools of `bench_accuracy.py`: `paper-clean`, noisy
and occluded `paper`, `street`; box and twobox), each sample's noisy mask is read as `infer` reads
it (its building's pieces, `masks.silhouette`), framed, and run once through the shipped network
of its true shape class (`Fitter.fit_framed`); the candidate's corners, peaks and ratio prior and
the mask's target completed by its Refiner (`cuboid.fit_start`, as `infer --cuboid` makes them)
then go to every optimiser in turn, mask by mask, so the machine's load falls on all of them
alike. Each fit is scored against the sample's truth (`cuboidtrain.geometry.accuracy`): mean corner
error per mask (mean / median over masks), hull against interior corners, the depth/height
relative error, the fitted silhouette's IoU with the mask, `wins` (the share of masks whose mean
corner error is below LM's by more than 0.05 px; `losses` the other way), and the median time of
the optimiser's call (its lift included, the target not: all share it), one thread.

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/accuracy/bench_optimizer.py --samples 100 \\
        --spools /tmp/spools300 --json bench-optimizer.json

The JSON: `command`, `threads`, `samples`, `variants` (name -> its settings), and `rows`, one per
(set, shape, variant): `set`, `shape`, `variant`, `masks`, `failed` (no finite fit),
`mean_px` / `median_px` (per-mask mean corner error, 256 px), `wins` / `losses` (against `lm`),
`iou_mean` / `iou_median`, `ms_median`, `evaluations_median` (soft fits: loss and gradient
evaluations), and `where.summarise`'s figures (`hull_mean_px`, `interior_median_px`,
`depth_height_median_rel`, ...).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from benchmarks.accuracy.bench_accuracy import SETS, spool_for
from cuboidtrain.fit.cuboid import FitStart, NonFiniteCuboid, check_finite, fit_start
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.geometry.camera_params import CuboidFit
from cuboidtrain.fit.masks import silhouette, to_mask
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry.mask_fit import ITERATIONS, fit_mask
from cuboidtrain.geometry.outline import MaskTarget
from cuboidtrain.geometry.soft_mask_fit import SoftSchedule, fit_soft
from cuboidtrain.geometry.accuracy import Truth, against_truth, summarise
from shared.sample import decode
from shared.shapes import Shape, get_shape
from shared.spool import enumerate_spool, read_sample_bytes

SHAPES = ("box", "twobox")
# The soft fit's schedules: its solver (L-BFGS per blur level, or Adam a step per level), its
# blur and its budget; 50 / 100 / 200 iterations show what more time buys it.
SCHEDULES = {
    "soft-lbfgs-50": SoftSchedule(iterations=50),
    "soft-lbfgs-100": SoftSchedule(iterations=100),
    "soft-lbfgs-200": SoftSchedule(iterations=200),
    "soft-lbfgs-100-wide": SoftSchedule(iterations=100, stages=4, sigma_start=4.0),  # a wider blur first
    "soft-adam-200": SoftSchedule(method="adam", iterations=200),
}
# LM's own budget: `lm` is the shipped one (mask_fit.ITERATIONS); more iterations tell whether the
# soft fit's gains come from its objective or only from solving longer.
LM_ITERATIONS = {"lm": ITERATIONS, "lm-50": 50}
DEFAULT_VARIANTS = ("lm", *SCHEDULES)
WIN_PX = 0.05  # a mask's corners closer than LM's by more than this count as a win


@dataclass(frozen=True)
class Outcome:
    """One optimiser on one mask: its fit (None: no finite fit), time and solver evaluations."""

    fit: CuboidFit | None
    ms: float
    evaluations: int | None


def run_variant(name: str, shape: Shape, start: FitStart) -> Outcome:
    """Fit `start`'s target with the named optimiser, timed."""
    began = time.perf_counter()
    evaluations = None
    try:
        if name in LM_ITERATIONS:
            fit = fit_mask(start.target, shape, start.corners, start.peaks, prior_ratios=start.prior_ratios,
                           iterations=LM_ITERATIONS[name])
        else:
            soft = fit_soft(start.target, shape, start.corners, start.peaks, prior_ratios=start.prior_ratios,
                            schedule=SCHEDULES[name])
            fit, evaluations = soft.fit, soft.evaluations
        ms = 1000 * (time.perf_counter() - began)
        check_finite(fit)
    except (NonFiniteCuboid, np.linalg.LinAlgError, ValueError):
        return Outcome(None, 1000 * (time.perf_counter() - began), evaluations)
    return Outcome(fit, ms, evaluations)


def masks_of(spool: Path, samples: int):
    """(building mask, truth) of the first `samples` samples, the mask as `infer` reads it."""
    for name in enumerate_spool(spool)[:samples]:
        sample = decode(read_sample_bytes(spool, name))
        building = silhouette(to_mask(sample.noisy.astype(np.uint8) * 255))
        if building is not None:
            yield building, Truth.of_sample(sample)


def measure_set(fitter: Fitter, spool: Path, samples: int, variants: tuple[str, ...],
                progress: Callable[[str], None]) -> dict[str, list[tuple[Outcome, Truth]]]:
    """Every variant on every mask of a spool, from the same network candidate, mask by mask."""
    model = fitter.models[0]
    shape = get_shape(model.shape)
    outcomes: dict[str, list[tuple[Outcome, Truth]]] = {v: [] for v in variants}
    for index, (building, truth) in enumerate(masks_of(spool, samples)):
        candidate = fitter.fit_framed(model, *fitter.framed(model, building))
        start = fit_start(candidate, MaskTarget.of(building))
        for name in variants:
            outcomes[name].append((run_variant(name, shape, start), truth))
        if index % 10 == 9:
            progress(f"{spool.name}: {index + 1} masks")
    return outcomes


def corner_error(outcome: Outcome, truth: Truth) -> float:
    if outcome.fit is None:
        return float("nan")
    return float(np.linalg.norm(outcome.fit.keypoints - truth.keypoints, axis=1).mean())


def row_of(scene: str, shape: str, name: str, results: list[tuple[Outcome, Truth]],
           baseline: list[tuple[Outcome, Truth]]) -> dict:
    """One table row: corner errors, where they are, IoU, time, and wins against LM."""
    errors = np.array([corner_error(o, t) for o, t in results])
    reference = np.array([corner_error(o, t) for o, t in baseline])
    done = [(o, t) for o, t in results if o.fit is not None]
    ious = np.array([o.fit.iou for o, _ in done])
    evaluations = [o.evaluations for o, _ in results if o.evaluations is not None]
    both = np.isfinite(errors) & np.isfinite(reference)
    return {"set": scene, "shape": shape, "variant": name, "masks": len(results), "failed": len(results) - len(done),
            "mean_px": float(np.nanmean(errors)), "median_px": float(np.nanmedian(errors)),
            "wins": float(np.mean(errors[both] < reference[both] - WIN_PX)),
            "losses": float(np.mean(errors[both] > reference[both] + WIN_PX)),
            "iou_mean": float(ious.mean()), "iou_median": float(np.median(ious)),
            "ms_median": statistics.median(o.ms for o, _ in results),
            "evaluations_median": statistics.median(evaluations) if evaluations else None} | summarise(
        [against_truth(o.fit.keypoints, o.fit.ratios, t, o.fit.camera) for o, t in done])


def show(result: dict) -> None:
    table = Table(title="Mask-fit optimisers from the same network candidate (256 px; mean / median over masks; "
                        "d/h: depth/height relative error; IoU: fitted silhouette with the mask; one thread)")
    for column in ("set", "shape", "optimiser", "masks", "corners px", "hull px", "interior px", "d/h median",
                   "IoU", "wins / losses vs LM", "ms median", "evals"):
        table.add_column(column)
    for r in result["rows"]:
        table.add_row(r["set"], r["shape"], r["variant"], f"{r['masks']}" + (f" ({r['failed']} failed)" if r["failed"] else ""),
                      f"{r['mean_px']:.2f} / {r['median_px']:.2f}", f"{r['hull_mean_px']:.2f} / {r['hull_median_px']:.2f}",
                      f"{r['interior_mean_px']:.2f} / {r['interior_median_px']:.2f}",
                      f"{100 * r['depth_height_median_rel']:.1f}%", f"{r['iou_mean']:.4f} / {r['iou_median']:.4f}",
                      "-" if r["variant"] == "lm" else f"{100 * r['wins']:.0f}% / {100 * r['losses']:.0f}%",
                      f"{r['ms_median']:.1f}", "-" if r["evaluations_median"] is None else f"{r['evaluations_median']:.0f}")
    Console(width=max(Console().width, 200)).print(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=100, help="masks per set and shape")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS),
                        choices=(*LM_ITERATIONS, *SCHEDULES), help="lm first: the others' wins are counted against it")
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.variants[0] != "lm":
        parser.error("--variants: lm first (the baseline of wins and losses)")
    torch.set_num_threads(args.threads)
    console = Console(stderr=True)
    rows = []
    for scene in args.sets:
        for shape in SHAPES:
            fitter = Fitter.from_shipped(FitOptions(shape=shape, cuboid=True, device="cpu"))
            spool = spool_for(args.spools, shape, scene, args.samples)
            outcomes = measure_set(fitter, spool, args.samples, tuple(args.variants), console.log)
            rows += [row_of(scene, shape, name, outcomes[name], outcomes["lm"]) for name in args.variants]
    result = {"command": " ".join(sys.argv), "threads": args.threads, "samples": args.samples,
              "variants": {name: asdict(SCHEDULES[name]) if name in SCHEDULES else {"lm_iterations": LM_ITERATIONS[name]}
                           for name in args.variants}, "rows": rows}
    show(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
