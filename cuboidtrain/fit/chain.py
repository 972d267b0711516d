"""Inference (paper 3.4): binary mask -> Refiner -> Estimator -> Tabulator -> keypoints.

The pieces of the fit path (`cuboidtrain.fit.fitter.Fitter` puts them together):
each input image is read, split into components and framed at the model's
resolution (`cuboidtrain.fit.masks`); the chain runs there and the keypoints go back
to the input's own pixels through the same Framing. The Refiner may be re-entered
on its own binarised output (Figure 7: each pass removes more occlusion). With
several models (one per shape class) the fit whose silhouette best explains the
input mask wins, the simpler class unless the richer one explains clearly more;
that IoU is the record's `confidence`.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from shared.errors import UsageError
from shared.raster import rasterize
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.files import write_json_atomically
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.fit.options import MAX_REFINE_STEPS
from shared.shapes import Shape, get_shape

log = logging.getLogger(__name__)

# "auto" distrusts a settled mask this far from the Refiner's first pass. On 300 noisy `paper`
# masks the shipped models' later passes only hurt (box: 10.16 px at one pass, 11.09 at two;
# auto 12.38 at 0.9, 10.43 at 0.99, 10.19 at 0.995; twobox 11.56, 11.89, 11.59, 11.56):
# auto keeps a later pass only when it barely moved the mask.
DRIFT_IOU = 0.995
# A twobox can lay its two parts end to end and pass for a box, so it explains any box
# silhouette about as well; it must beat the box by this much IoU to be chosen. On 240
# mixed noisy 64 px samples (CPU recipe models), 0.02 gave 86% right against 82% at 0.
RICHER_SHAPE_MARGIN = 0.02


def binarise(refined: torch.Tensor) -> torch.Tensor:
    """Tanh output -> the +-1 mask the Refiner was trained on (> 0 is object, as everywhere)."""
    return torch.where(refined > 0, 1.0, -1.0).to(refined.dtype)


def refine(model: CuboidNet, mask_pm1: torch.Tensor, steps: int | None,
           max_steps: int = MAX_REFINE_STEPS) -> tuple[torch.Tensor, int, bool]:
    """Iterative refinement (Figure 7): (B, 1, S, S) +-1 masks -> (refined tanh output, passes
    run, whether every mask converged).

    `steps=K` runs R K times, each pass on the sign of the previous output (R was
    trained on binary inputs, not tanh values); K=0 hands the raw mask on. `None`
    ("auto") repeats, per mask, until a pass flips none of its pixels. A mask whose
    Refiner never settles within `max_steps` passes, or settles far from its first
    pass (IoU below DRIFT_IOU: grown into a square, eaten away), is not trusted:
    auto then keeps its first pass (one pass is what R was trained to do). A fixed K
    always counts as converged. Passes run is the most any mask of the batch took.
    """
    if steps is not None:  # a count FitOptions has checked
        refined = mask_pm1
        for _ in range(steps):
            refined = model.refiner(binarise(refined))
        return refined, steps, True
    batch = mask_pm1.shape[0]
    settled_at = torch.zeros(batch, dtype=torch.long)  # 0: not settled yet
    refined, first, result, previous = mask_pm1, None, None, None
    for step in range(1, max_steps + 1):
        refined = model.refiner(binarise(refined))
        current = refined > 0
        if first is None:
            first, result = refined, refined.clone()
        else:
            settled = (current == previous).flatten(1).all(1) & (settled_at == 0)
            result[settled], settled_at[settled] = refined[settled], step
            if (settled_at > 0).all():
                break
        previous = current
    trusted = (settled_at > 0) & (mask_iou(result, first) >= DRIFT_IOU)
    result[~trusted], settled_at[~trusted] = first[~trusted], 1
    return result, int(settled_at.max()), bool(trusted.all())


def mask_iou(refined: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) masks in +-1 (object > 0) -> (B,) IoU; two empty masks agree fully (1)."""
    a, b = (refined > 0).flatten(1), (clean > 0).flatten(1)
    inter, union = (a & b).sum(1).float(), (a | b).sum(1).float()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


def chain(model: CuboidNet, x1: torch.Tensor, refine_steps: int | None = 1) -> dict:
    """T(S(R^K(x1))), the inference chain of paper 3.4, on a (B, 1, S, S) +-1 batch, with K
    Refiner passes (None: until settled). Returns refined, heatmaps, keypoints (T's), ratios
    and the passes run."""
    if refine_steps == 1:  # one pass on a binary mask is the model's own forward
        return model(x1) | {"refine_steps": 1, "refine_converged": True}
    refined, steps_run, converged = refine(model, x1, refine_steps)
    heatmaps = model.estimator(refined)  # S sees R's tanh output, as in CuboidNet.forward and training
    keypoints, ratios = model.tabulator(heatmaps)
    return {"refined": refined, "heatmaps": heatmaps, "keypoints": keypoints, "ratios": ratios,
            "refine_steps": steps_run, "refine_converged": converged}


def silhouette(shape: str | Shape, keypoints: np.ndarray, size: int) -> np.ndarray:
    """The fitted cuboid's bool (S, S) silhouette: the union of its parts' convex hulls,
    drawn by the generator's own rasteriser so a perfect fit reproduces a training mask."""
    geometry = get_shape(shape) if isinstance(shape, str) else shape
    return rasterize(geometry, np.asarray(keypoints, dtype=np.float64), size)


def confidence(shape: str | Shape, keypoints: np.ndarray, mask) -> float:
    """IoU of the fitted silhouette with `mask` (> 0: the framed input), in [0, 1].

    The Tabulator outputs a geometrically valid cuboid (or two-box) whatever it is
    shown, so when that silhouette explains the input well, the model's shape class
    fits the building. A box forced onto a two-box building must leave one wing
    uncovered or overhang the notch between them, and the IoU drops; a heavily
    occluded or non-cuboid mask lowers it as well. The target is the input, not
    each model's refined mask: each Refiner pulls the mask towards its own class,
    so judging a model against its own refinement flatters it (on 240 mixed
    samples, choosing by the refined masks was right 80% of the time, by the input 86%).
    """
    target = np.asarray(mask.detach().cpu() if torch.is_tensor(mask) else mask).squeeze() > 0
    fitted = silhouette(shape, keypoints, target.shape[-1])
    union = np.logical_or(fitted, target).sum()
    return float(np.logical_and(fitted, target).sum() / union) if union else 0.0


def load_models(paths: list[Path]) -> list[CuboidNet]:
    """One model per checkpoint, at most one per shape class (the error names both files)."""
    models, seen = [], {}
    for path in paths:
        model, _ = load_model(path)
        if model.shape in seen:
            raise UsageError(f"--checkpoint {path}: a second {model.shape!r} model ({seen[model.shape]} is one "
                             f"already); give at most one checkpoint per shape class")
        seen[model.shape] = path
        models.append(model)
    return models


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


def trust(record: dict, mask: np.ndarray, keypoints: np.ndarray, shape: str) -> None:
    """Lower the record's confidence, and say why, where the fit explains less than its IoU claims:
    corners outside the input are guessed, a silhouette cut by the image's edge hides its outline
    (a mask filling the frame shows none of it), and a Refiner that did not settle was not used."""
    outside = outside_keypoints(keypoints, mask.shape)
    if outside.size:
        names = get_shape(shape).keypoint_names
        record["warnings"].append(f"{outside.size} of {len(keypoints)} keypoints lie outside the input image "
                                  f"({', '.join(names[i] for i in outside)}): guessed, not seen")
        record["confidence"] *= 1 - outside.size / len(keypoints)
    cut = border_cut(mask)
    record["confidence"] *= 1 - cut
    if cut >= 0.5:
        record["warnings"].append(f"{100 * cut:.0f}% of the silhouette's outline lies on the image's edge: "
                                  f"the mask may not show a building's outline at all")


def choose(fits: list[tuple]) -> tuple:
    """The best-explained fit: simplest class first (fewest keypoints), replaced by a richer one
    only when its confidence is higher by more than RICHER_SHAPE_MARGIN."""
    ordered = sorted(fits, key=lambda f: get_shape(f[0]["shape"]).num_keypoints)
    best = ordered[0]
    for candidate in ordered[1:]:
        if candidate[0]["confidence"] > best[0]["confidence"] + RICHER_SHAPE_MARGIN:
            best = candidate
    return best


def error_record(path: str, reason: str, all_components: bool) -> dict:
    record = {"input": path, "shape": None, "confidence": None, "keypoints": None, "ratios": None,
              "refine_steps": None, "refine_converged": None, "error": reason, "warnings": [], "candidates": {}}
    return record | ({"component": None} if all_components else {})


def write_records(path: Path, records: list[dict]) -> None:
    """The JSON list, replaced atomically: a reader never sees half of it."""
    write_json_atomically(path, records, indent=2)
