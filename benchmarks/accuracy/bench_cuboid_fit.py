"""The `--cuboid` stage's mechanisms, each measured on and off on the same masks (issue 20).

For each set (`paper-clean`, noisy and occluded `paper`, `street`) and shape class, the first
--samples masks after --offset of the seeded 256 px validation spools (bench_accuracy's) are
framed and run through both shipped models once; every variant then fits cuboids from those
same candidates (`cuboid.fit_candidates`, a batch at a time) and is scored against the truth:

* the Refiner's completion (`fit/completion.py`) on (shipped) and off: corner error of the
  mask's own class, hull and interior corners, depth/height;
* shape selection from the fitted cuboids (`cuboid.choose_cuboid`, shipped: a 0.005 IoU margin
  and a twobox of nearly equal heights set aside) against the IoU alone with the networks'
  margin (0.02) and with 0.005.

Use --offset to score masks the mechanisms were not tuned on (they were tuned on the first 100).

    .venv/bin/python benchmarks/accuracy/bench_cuboid_fit.py --samples 200 --offset 100 --json bench-cuboid-fit.json
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from bench_accuracy import spool_for
from cuboidtrain.fit.candidates import RICHER_SHAPE_MARGIN, choose
from cuboidtrain.fit.cuboid import CUBOID_MARGIN, choose_cuboid, fit_candidates
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.masks import silhouette
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry.outline import MaskTarget
from cuboidtrain.geometry.accuracy import Truth, hull_corners
from shared.sample import decode
from shared.spool import enumerate_spool, read_sample_bytes

SETS = [(scene, shape) for scene in ("paper-clean", "paper", "street") for shape in ("box", "twobox")]
BATCH = 32
RULES = {f"IoU, margin {RICHER_SHAPE_MARGIN}": lambda c, f: choose(judged(c, f), RICHER_SHAPE_MARGIN),
         f"IoU, margin {CUBOID_MARGIN}": lambda c, f: choose(judged(c, f), CUBOID_MARGIN),
         "shipped: margin + seam gate": lambda c, f: choose_cuboid(c, f)[0]}


def judged(candidates, fitted):
    return [replace(c, confidence=fitted[c.shape].fit.iou) for c in candidates]


def masks_and_candidates(fitter: Fitter, spools: Path, scene: str, shape: str, offset: int, samples: int):
    """Each mask's building silhouette, both models' candidates, and its truth."""
    spool = spool_for(spools, shape, scene, offset + samples)
    items = []
    for name in enumerate_spool(spool)[offset : offset + samples]:
        sample = decode(read_sample_bytes(spool, name))
        mask = silhouette(sample.noisy.astype(bool))
        candidates = [fitter.fit_framed(model, *fitter.framed(model, mask)) for model in fitter.models]
        items.append((mask, candidates, Truth.of_sample(sample)))
    return items


def fit_all(items, completion: bool) -> list[dict]:
    """Every mask's fitted cuboid of each class, a batch of masks at a time."""
    fitted = []
    for start in range(0, len(items), BATCH):
        chunk = items[start : start + BATCH]
        pairs = [(c, MaskTarget.of(mask)) for mask, candidates, _ in chunk for c in candidates]
        flat = iter(fit_candidates([c for c, _ in pairs], [t for _, t in pairs], completion=completion))
        fitted += [{c.shape: next(flat) for c in candidates} for _, candidates, _ in chunk]
    return fitted


def corner_figures(items, fitted, shape: str) -> dict:
    errors, hull, interior, depth = [], [], [], []
    for (_, _, truth), fits in zip(items, fitted):
        fit = fits[shape].fit
        error = np.linalg.norm(fit.keypoints - truth.keypoints, axis=1)
        on_hull = hull_corners(truth.keypoints)
        errors.append(error.mean())
        hull += list(error[on_hull])
        interior += list(error[~on_hull])
        depth.append(abs(truth.shape.ratio_vector(fit.ratios)[0] / truth.shape.ratio_vector(truth.ratios)[0] - 1))
    return {"mean_px": float(np.mean(errors)), "median_px": float(np.median(errors)), "hull_mean_px": float(np.mean(hull)),
            "interior_mean_px": float(np.mean(interior)), "depth_height_median_rel": float(np.median(depth))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=100, help="masks per set and shape")
    parser.add_argument("--offset", type=int, default=0, help="skip this many masks of each spool")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    completion, selection = [], {rule: {} for rule in RULES}
    for scene, shape in SETS:
        items = masks_and_candidates(fitter, args.spools, scene, shape, args.offset, args.samples)
        fitted = {on: fit_all(items, completion=on) for on in (True, False)}
        completion.append({"set": scene, "shape": shape, "samples": len(items),
                           "on": corner_figures(items, fitted[True], shape),
                           "off": corner_figures(items, fitted[False], shape)})
        for rule, pick in RULES.items():
            right = [pick(candidates, fits).shape == shape for (_, candidates, _), fits in zip(items, fitted[True])]
            selection[rule][f"{scene}/{shape}"] = float(np.mean(right))
    result = {"command": " ".join(sys.argv), "completion": completion, "selection": selection}
    show(result)
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


def show(result: dict) -> None:
    table = Table(title="The Refiner's completion, off -> on (mean px at 256; d/h median relative error)")
    for column in ("set", "shape", "masks", "mean", "median", "hull", "interior", "d/h"):
        table.add_column(column, justify="right")
    for row in result["completion"]:
        off, on = row["off"], row["on"]
        cells = [f"{off[k]:.2f} -> {on[k]:.2f}" for k in ("mean_px", "median_px", "hull_mean_px", "interior_mean_px")]
        d = "depth_height_median_rel"
        table.add_row(row["set"], row["shape"], str(row["samples"]), *cells, f"{100 * off[d]:.1f}% -> {100 * on[d]:.1f}%")
    selection = Table(title="Shape selection from the fitted cuboids: share of masks given their true class")
    sets = list(next(iter(result["selection"].values())))
    selection.add_column("rule")
    for name in sets:
        selection.add_column(name, justify="right")
    for rule, shares in result["selection"].items():
        selection.add_row(rule, *[f"{100 * shares[s]:.1f}%" for s in sets])
    console = Console(width=160)
    console.print(table)
    console.print(selection)


if __name__ == "__main__":
    main()
