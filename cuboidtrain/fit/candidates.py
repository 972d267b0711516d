"""The fit path's steps around the chain and the typed results they hand on: candidates, their choice, their scores.

The Fitter (`cuboidtrain.fit.fitter`) puts these together: each input image is
read, split into components and framed at every model's resolution
(`cuboidtrain.fit.masks`); the chain runs there (`CuboidNet.forward`, refinement
in `cuboidtrain.models.refine`) and gives one `Candidate` per shape class. The
candidate whose silhouette best explains the input mask wins (`choose`), the
simpler class unless the richer one explains clearly more; that IoU, lowered
where the fit is guessed (`assess`), is the record's `confidence`. The stages
hand each other frozen dataclasses: none edits another's result.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from cuboidtrain.fit.masks import Framing
from cuboidtrain.models.refine import DRIFT_IOU
from cuboidtrain.models.settings import MAX_REFINE_STEPS
from shared.shapes import get_shape

log = logging.getLogger(__name__)

# A twobox can lay its two parts end to end and pass for a box, so it explains any box
# silhouette about as well; it must beat the box by this much IoU to be chosen. On 240
# mixed noisy 64 px samples (CPU recipe models), 0.02 gave 86% right against 82% at 0.
RICHER_SHAPE_MARGIN = 0.02


@dataclass(frozen=True)
class Candidate:
    """One shape class's fit of one framed mask, at model resolution (`Fitter.fit_framed`)."""

    shape: str
    keypoints: np.ndarray  # (N, 2) model px, as the extractor read them
    ratios: dict[str, float]
    confidence: float  # IoU of the fitted silhouette with the framed input (`confidence`)
    refine_steps: int  # Refiner passes run
    refine_converged: bool
    refined: np.ndarray  # (S, S) R's tanh output: what an explanation draws
    heatmaps: np.ndarray  # (N, S, S) S's maps
    framed: np.ndarray  # (S, S) bool, or float in [0, 1] for a grey-input model: the framed input x1 the chain saw
    framing: Framing | None = None  # input px <-> model px; None for a mask framed by the caller


@dataclass(frozen=True)
class Scores:
    """How far the chosen candidate is trusted: its confidence lowered where the fit is guessed, and why."""

    confidence: float  # in [0, 1]
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class Explanation:
    """What an explanation panel draws (`cuboidtrain.infer.explain`): the winning candidate and the input."""

    candidate: Candidate
    mask: np.ndarray  # (H, W) bool: the fitted component in the input's own pixels


def border_warnings(mask: np.ndarray) -> list[str]:
    """A silhouette cut by the image's edge is a truncated building: its hidden corners are guessed."""
    sides = {"top": mask[0].any(), "bottom": mask[-1].any(), "left": mask[:, 0].any(), "right": mask[:, -1].any()}
    touched = [side for side, hit in sides.items() if hit]
    if not touched:
        return []
    return [f"silhouette touches the image's {' and '.join(touched)} border: the building may be truncated "
            f"there, and keypoints beyond the border are extrapolated"]


def border_cut(mask: np.ndarray) -> float:
    """The share of the silhouette's bounding box outline that lies on the image's edge, in [0, 1]:
    0 for a building seen whole, 1 for a mask that fills the frame (nothing of its outline is seen)."""
    x, y, w, h = cv2.boundingRect(mask.astype(np.uint8))
    on_edge = (mask[0].sum() + mask[-1].sum()) + (mask[:, 0].sum() + mask[:, -1].sum())
    return float(min(on_edge / (2 * (w + h)), 1.0))


def outside_keypoints(keypoints: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Indices of the (N, 2) keypoints that lie outside the (H, W) image (pixel centres 0 .. W-1)."""
    height, width = shape
    x, y = keypoints[:, 0], keypoints[:, 1]
    return np.flatnonzero((x < -0.5) | (x > width - 0.5) | (y < -0.5) | (y > height - 0.5))


def assess(candidate: Candidate, mask: np.ndarray, keypoints: np.ndarray) -> Scores:
    """The chosen candidate's confidence, lowered, and the warnings saying why, where the fit
    explains less than its IoU claims: corners outside the input are guessed, a silhouette cut by
    the image's edge hides its outline (a mask filling the frame shows none of it), and a Refiner
    that did not settle was not used. `mask` is the input component, `keypoints` in its pixels."""
    confidence, warnings = candidate.confidence, border_warnings(mask)
    if not candidate.refine_converged:
        warnings.append(f"refinement did not settle within {MAX_REFINE_STEPS} passes, or drifted "
                        f"from its first pass (IoU < {DRIFT_IOU}): its first pass was used")
    outside = outside_keypoints(keypoints, mask.shape)
    if outside.size:
        names = get_shape(candidate.shape).keypoint_names
        warnings.append(f"{outside.size} of {len(keypoints)} keypoints lie outside the input image "
                        f"({', '.join(names[i] for i in outside)}): guessed, not seen")
        confidence *= 1 - outside.size / len(keypoints)
    cut = border_cut(mask)
    confidence *= 1 - cut
    if cut >= 0.5:
        warnings.append(f"{100 * cut:.0f}% of the silhouette's outline lies on the image's edge: "
                        f"the mask may not show a building's outline at all")
    return Scores(confidence=confidence, warnings=tuple(warnings))


def choose(candidates: list[Candidate], margin: float = RICHER_SHAPE_MARGIN) -> Candidate:
    """The best-explained candidate: simplest class first (fewest keypoints), replaced by a richer
    one only when its confidence is higher by more than `margin`."""
    ordered = sorted(candidates, key=lambda c: get_shape(c.shape).num_keypoints)
    best = ordered[0]
    for candidate in ordered[1:]:
        if candidate.confidence > best.confidence + margin:
            best = candidate
    return best
