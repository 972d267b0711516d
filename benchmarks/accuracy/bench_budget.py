"""The corners' error budget: each stage of `infer --cuboid` replaced by its oracle in turn (issue 37, Must have 1).

On the seeded 256 px validation spools of bench_accuracy.py (`paper-clean`, `paper`,
`street`; box and twobox, each through the model of its own class), every mask is fitted
as `infer --cuboid` fits it (`Fitter` with `FitOptions(cuboid=True)`, the plausible camera),
then with one stage after another given by the truth:

* `networks`: today's pipeline, nothing given;
* `clean mask`: the true clean mask in the Refiner's output's place, framed as the networks
  see the noisy one (`fitter.Oracle.refined`); S, T and the cuboid fit run as before;
* `heat maps`: the true heat maps in the Estimator's place: Gaussians at the true corners in
  model px, of the model's sigma, as the training targets are made (`fitter.Oracle.keypoints`);
  T reads them, the cuboid fit runs on the noisy mask as before;
* `outline 1 px`, `outline 2 px`: the true outline corners (the true keypoints' hull,
  `accuracy.hull_corners`) plus Gaussian noise of that sd, lifted to a cuboid (`lift.lift`) with
  the interior corners weighted 0: what the outline alone gives. The interior corners are the
  lift's start only, at the truth, so the discrete choices the outline leaves (which interior
  corner is in front, a face seen edge-on) are the truth's: a bound, not a method;
* `silhouette`: the cuboid fitted to the true clean mask at 256 px (`mask_fit.fit_masks`, the
  corners' pull 0, no ratio anchor) started from the true corners: the silhouette's own limit.

Each row: corner error in 256 px, all corners (mean / median of the per-mask mean, as
bench_accuracy's `infer`), the outline (hull) and interior corners pooled (mean, median, p90),
and the depth/height median relative error, the camera free (plausible, `infer`'s default) and
given (each mask's true focal length and principal point, `KnownCamera`). The corners are the
free fit's (the outline's lift with a free camera leaves the interior far off where the outline
has four corners: `street`'s level views), but the `silhouette`'s, which are the true camera's. With `silhouette`, two shares of masks the silhouette cannot decide:

* `edge-on`: a face of the true box (of either part) is less than EDGE_ON_PX wide in the
  picture (its projected area over its longest side): the silhouette hides where its edge is;
* `Necker`: started from the true corners with the interior ones reflected through the outline
  corners' centre (the other interior corner in front, for a box in near-affine view), the fit
  with the true camera explains the clean mask as well (IoU within NECKER_IOU) with an interior
  corner more than NECKER_PX from the first fit's.

    .venv/bin/python benchmarks/accuracy/bench_budget.py --samples 100 --threads 1 --json budget.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from bench_accuracy import SETS, spool_for
from cuboidtrain.fit.fitter import Fitter, Oracle
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry.accuracy import Truth, corner_errors, hull_corners
from cuboidtrain.geometry.camera_params import describe
from cuboidtrain.geometry.intrinsics import KnownCamera
from cuboidtrain.geometry.lift import lift
from cuboidtrain.geometry.mask_fit import fit_masks
from cuboidtrain.geometry.outline import MaskFitWeights, MaskTarget
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.zoo import default_checkpoints
from shared.sample import decode
from shared.shapes import get_shape
from shared.spool import enumerate_spool, read_sample_bytes

STAGES = ("networks", "clean mask", "heat maps", "outline 1 px", "outline 2 px", "silhouette")
NOISE_PX = {"outline 1 px": 1.0, "outline 2 px": 2.0}
EDGE_ON_PX = 1.0
NECKER_IOU = 0.002
NECKER_PX = 2.0
SILHOUETTE_ONLY = replace(MaskFitWeights(), corners=0.0)  # the silhouette alone: no pull toward any corner


@dataclass(frozen=True)
class Answer:
    """One stage's answer for one mask: its corners (input px, viewer-named) and ratios, camera free;
    its ratios with the camera given."""

    keypoints: np.ndarray
    ratios: dict
    ratios_given: dict


def read_samples(spool: Path, count: int) -> list:
    samples = [decode(read_sample_bytes(spool, name)) for name in enumerate_spool(spool)[:count]]
    if len(samples) < count:
        raise SystemExit(f"{spool}: {len(samples)} samples, expected {count}")
    return samples


def through_fitter(fitter: Fitter, sample, truth: Truth, oracle: Oracle | None) -> Answer:
    """`infer --cuboid`'s answer for the sample's noisy mask, camera free and given, with `oracle`'s stages."""
    mask = sample.noisy.astype(np.uint8) * 255
    free = fitter.fit(mask, oracle=oracle)
    given = fitter.fit(mask, camera=truth.known_camera(), oracle=oracle)
    return Answer(free.keypoints, free.ratios, given.ratios)


def lifted(truth: Truth, sigma: float, rng: np.random.Generator) -> Answer:
    """The true outline corners plus noise of `sigma` px lifted, the interior corners weighted 0."""
    outline = hull_corners(truth.keypoints)
    points = truth.keypoints + np.where(outline[:, None], rng.normal(0, sigma, truth.keypoints.shape), 0.0)
    weights = outline.astype(np.float64)
    answers = [describe(lift(points, truth.shape, weights, known=known, frame=(256, 256)).camera, 0.0)
               for known in (None, truth.known_camera())]
    return Answer(answers[0].keypoints, answers[0].ratios, answers[1].ratios)


def silhouette_fit(target: MaskTarget, truth: Truth, corners: np.ndarray, known: KnownCamera | None):
    """The cuboid that explains the clean mask alone, started from `corners`; the true camera where `known`."""
    shape = truth.shape
    return fit_masks([target], shape, corners[None], np.ones((1, shape.num_keypoints)), [None], SILHOUETTE_ONLY,
                     known=[known], plausible=known is None)[0]


def silhouette(sample, truth: Truth) -> tuple[Answer, bool, bool]:
    """The silhouette's own limit, and whether the mask is Necker-ambiguous and has a face edge-on."""
    target = MaskTarget.of(sample.clean)
    known = truth.known_camera()
    free, given = (silhouette_fit(target, truth, truth.keypoints, k) for k in (None, known))
    interior = ~hull_corners(truth.keypoints)
    flipped = truth.keypoints.copy()
    centre = truth.keypoints[~interior].mean(0)
    flipped[interior] = 2 * centre - truth.keypoints[interior]
    other = silhouette_fit(target, truth, flipped, known)
    apart = np.linalg.norm(other.keypoints[interior] - given.keypoints[interior], axis=1).max() if interior.any() else 0.0
    necker = bool(other.iou >= given.iou - NECKER_IOU and apart > NECKER_PX)
    return Answer(given.keypoints, free.ratios, given.ratios), necker, edge_on(truth)


def edge_on(truth: Truth) -> bool:
    """Whether a face of any part of the true solid is under EDGE_ON_PX wide in the picture."""
    for part in truth.shape.parts:
        corners = truth.keypoints[list(part)]
        for axis in range(3):  # a part's corner c has sides (left, bottom, front) = bits 1, 0, 2 of c
            bit = (1, 0, 2)[axis]
            for side in (0, 1):
                face = [c for c in range(8) if (c >> bit) & 1 == side]
                a, b = (x for x in (0, 1, 2) if x != bit)
                ring = sorted(face, key=lambda c: ((c >> a) & 1, ((c >> b) & 1) ^ ((c >> a) & 1)))
                quad = corners[ring]
                area = 0.5 * abs(np.cross(quad[2] - quad[0], quad[3] - quad[1]))
                longest = max(np.linalg.norm(quad[i] - quad[i - 1]) for i in range(4))
                if area / max(longest, 1e-9) < EDGE_ON_PX:
                    return True
    return False


def row_figures(answers: list[Answer], truths: list[Truth]) -> dict:
    """The row's corner and depth/height figures over its masks."""
    outline, interior, per_mask, free, given = [], [], [], [], []
    for answer, truth in zip(answers, truths):
        errors = corner_errors(truth.shape, answer.keypoints, truth.keypoints, answer.ratios, truth.ratios)
        outline.append(errors.hull)
        interior.append(errors.interior)
        per_mask.append(np.concatenate([errors.hull, errors.interior]).mean())
        free.append(errors.depth_height)
        given.append(corner_errors(truth.shape, answer.keypoints, truth.keypoints, answer.ratios_given,
                                   truth.ratios).depth_height)
    figures = {"all_mean_px": float(np.mean(per_mask)), "all_median_px": float(np.median(per_mask))}
    for name, values in (("outline", outline), ("interior", interior)):
        pooled = np.concatenate(values)
        figures |= {f"{name}_mean_px": float(pooled.mean()), f"{name}_median_px": float(np.median(pooled)),
                    f"{name}_p90_px": float(np.percentile(pooled, 90))}
    figures["dh_free_median"] = float(np.median(np.concatenate(free)))
    figures["dh_given_median"] = float(np.median(np.concatenate(given)))
    return figures


def budget(model, samples: list, seed: int, stages=STAGES) -> list[dict]:
    """Every stage's row for one set and shape."""
    fitter = Fitter([model], FitOptions(device="cpu", cuboid=True, shape=model.shape))
    truths = [Truth.of_sample(s) for s in samples]
    rng = np.random.default_rng(seed)
    rows = []
    for stage in stages:
        start = time.perf_counter()
        extra = {}
        if stage in NOISE_PX:
            answers = [lifted(t, NOISE_PX[stage], rng) for t in truths]
        elif stage == "silhouette":
            limits = [silhouette(s, t) for s, t in zip(samples, truths)]
            answers = [a for a, _, _ in limits]
            extra = {"necker": float(np.mean([n for _, n, _ in limits])),
                     "edge_on": float(np.mean([e for _, _, e in limits]))}
        else:
            oracles = {"networks": lambda s, t: None, "clean mask": lambda s, t: Oracle(refined=s.clean),
                       "heat maps": lambda s, t: Oracle(keypoints=t.keypoints)}[stage]
            answers = [through_fitter(fitter, s, t, oracles(s, t)) for s, t in zip(samples, truths)]
        rows.append({"stage": stage, "samples": len(samples), **row_figures(answers, truths), **extra,
                     "seconds": time.perf_counter() - start})
    return rows


def show(rows: list[dict]) -> None:
    """The table as BENCHMARKS.md has it (markdown)."""
    print("| set | shape | stage | all mean / median | outline mean / median / p90 | interior mean / median / p90 "
          "| d/h median free / given |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        extra = f" (Necker {100 * r['necker']:.0f}%, edge-on {100 * r['edge_on']:.0f}%)" if "necker" in r else ""
        print(f"| {r['set']} | {r['shape']} | {r['stage']}{extra} | {r['all_mean_px']:.2f} / {r['all_median_px']:.2f} "
              f"| {r['outline_mean_px']:.2f} / {r['outline_median_px']:.2f} / {r['outline_p90_px']:.2f} "
              f"| {r['interior_mean_px']:.2f} / {r['interior_median_px']:.2f} / {r['interior_p90_px']:.2f} "
              f"| {100 * r['dh_free_median']:.1f}% / {100 * r['dh_given_median']:.1f}% |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=100, help="masks per set and shape")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sets", nargs="*", default=list(SETS), choices=SETS)
    parser.add_argument("--stages", nargs="*", default=list(STAGES), choices=STAGES)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    models = {m.shape: m for m in (load_model(p)[0] for p in default_checkpoints(None))}
    rows = []
    for scene in args.sets:
        for number, (shape, model) in enumerate(models.items()):
            samples = read_samples(spool_for(args.spools, shape, scene, args.samples), args.samples)
            rows += [{"set": scene, "shape": shape} | r for r in budget(model, samples, number, args.stages)]
            print(f"{scene} {shape}: done", file=sys.stderr, flush=True)
    show(rows)
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
