"""The `--cuboid` stage: a network candidate -> the perspective cuboid fitted to the input mask.

With `FitOptions(cuboid=True)` (`cuboidtrain infer --cuboid`) the Fitter hands every shape
class's Candidate here with the input component: the networks' corners, mapped back to the
input's pixels, start `cuboidtrain.fit.outline.fit_mask` at the input's own resolution and
pull the corners the outline leaves free, each weighted by its heat map's peak; the
Tabulator's ratios anchor the extents. The record's keypoints are then the fitted box's
projection, its ratios the box's own, and the shape class is chosen by the fitted
silhouettes' IoU with the input (`chain.choose`, same margin).

Measured (BENCHMARKS.md, "infer --cuboid"): clean masks gain strongly, noisy and occluded
ones little; depth/height gets worse. Hence opt-in.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cuboidtrain.fit.chain import Candidate
from cuboidtrain.fit.geometry import CuboidFit
from cuboidtrain.fit.outline import MaskTarget, bilinear, fit_mask
from shared.shapes import get_shape

# An outline corner's score falls with its distance to the input's outline, at this scale:
# a clean 256 px mask puts its fitted corners within about 1 px of it (rasterised corners).
CORNER_SCORE_PX = 2.0


class NonFiniteCuboid(ValueError):
    """The cuboid fit gave NaN or Infinity where the record needs a number: no fit, and in
    `Fitter.records` an error record (never a networks-only record in its place)."""


@dataclass(frozen=True)
class FittedCuboid:
    """One shape class's cuboid fitted to the input, and how far each of its corners is seen."""

    fit: CuboidFit  # keypoints (N, 2) input px, viewer-named; ratios; angles; intrinsics; IoU
    corner_scores: np.ndarray  # (N,) in [0, 1], viewer-named (`corner_scores`)

    def record(self) -> dict:
        """The infer record's `cuboid` object (docs/contract.md, "The cuboid object")."""
        fit = self.fit
        perspective = math.isfinite(fit.focal_px)  # inf: weak perspective, no focal length or principal point
        return {"yaw_deg": fit.yaw_deg, "pitch_deg": fit.pitch_deg, "roll_deg": fit.roll_deg,
                "focal_px": fit.focal_px if perspective else None,
                "principal_px": list(fit.principal_px) if perspective else None,
                "mirror": fit.mirror, "iou": fit.iou, "outline_rms_px": fit.residual_px,
                "corners": [{"on_outline": bool(on), "score": float(s)}
                            for on, s in zip(fit.on_outline, self.corner_scores)]}


def fit_candidate(candidate: Candidate, mask: np.ndarray | MaskTarget) -> FittedCuboid:
    """The cuboid of `candidate`'s class fitted to `mask` (H, W) bool, the input component (or its
    MaskTarget, shared by the shape classes tried)."""
    if candidate.framing is None:
        raise ValueError("a cuboid fit needs the candidate's framing: the map back to the input's pixels")
    shape = get_shape(candidate.shape)
    corners = candidate.framing.to_input(candidate.keypoints)
    peaks = heatmap_peaks(candidate.heatmaps)
    prior = shape.ratio_vector(candidate.ratios)
    # The Tabulator's head is unbounded: a ratio <= 0 anchors nothing (its log is -inf or NaN), so no anchor then.
    prior = prior if (prior > 0).all() and np.isfinite(prior).all() else None
    target = mask if isinstance(mask, MaskTarget) else MaskTarget.of(mask)
    fit = fit_mask(target, shape, corners, peaks, prior_ratios=prior)
    check_finite(fit)
    named_peaks = peaks[fit.camera.naming()]  # the fit's corner i is the network's corner naming()[i]
    return FittedCuboid(fit, corner_scores(fit, target.sdf, named_peaks))


def heatmap_peaks(heatmaps: np.ndarray) -> np.ndarray:
    """(N, S, S) -> (N,) each map's maximum in [0, 1]: S's confidence in its corner (codec.peak_scores)."""
    return np.clip(heatmaps.reshape(len(heatmaps), -1).max(1).astype(np.float64), 0.0, 1.0)


def corner_scores(fit: CuboidFit, sdf: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """(N,) in [0, 1]: a corner the fitted outline shows scores by how close it lies to the input's
    outline (an occluder that removed it lowers it); a hidden one keeps its heat map's peak, the
    only evidence there is for it."""
    distance = np.abs(bilinear(sdf, fit.keypoints))  # sdf: the input's signed distance to its outline
    seen = np.exp(-0.5 * (distance / CORNER_SCORE_PX) ** 2)
    return np.where(fit.on_outline, seen, peaks)


def check_finite(fit: CuboidFit) -> None:
    """NonFiniteCuboid naming the first number of the fit that is NaN or Infinity (focal length
    excepted: infinite is weak perspective, written as null)."""
    numbers = {"keypoints": fit.keypoints, "ratios": get_shape(fit.shape).ratio_vector(fit.ratios),
               "yaw/pitch/roll": [fit.yaw_deg, fit.pitch_deg, fit.roll_deg], "principal point": fit.principal_px,
               "IoU": [fit.iou], "outline residual": [fit.residual_px]}
    for name, values in numbers.items():
        if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
            raise NonFiniteCuboid(f"the {fit.shape} cuboid fit's {name} is not finite (NaN or Infinity): no fit")
    if math.isnan(fit.focal_px):
        raise NonFiniteCuboid(f"the {fit.shape} cuboid fit's focal length is NaN: no fit")
