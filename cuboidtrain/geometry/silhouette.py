"""A fitted cuboid's silhouette and how well it explains a mask (IoU), drawn by the generator's rasteriser."""
from __future__ import annotations

import cv2
import numpy as np

from shared.raster import rasterize
from shared.shapes import Shape, get_shape


def model_silhouette(shape: str | Shape, keypoints: np.ndarray, size: int | tuple[int, int]) -> np.ndarray:
    """The fitted cuboid's bool (S, S) silhouette, or (H, W) for an input's pixels: the union of
    its parts' convex hulls, drawn by the generator's own rasteriser so a perfect fit reproduces
    a training mask. (Not `masks.silhouette`, which picks the building out of an input mask.)"""
    geometry = get_shape(shape) if isinstance(shape, str) else shape
    height, width = (size, size) if isinstance(size, int) else size
    # The rasteriser draws squares: an (H, W) image is the top left of its longer side's square.
    return rasterize(geometry, np.asarray(keypoints, dtype=np.float64), max(height, width))[:height, :width]


def confidence(shape: str | Shape, keypoints: np.ndarray, mask) -> float:
    """IoU of the fitted silhouette with `mask` (> 0: the framed input, or any input's (H, W)), in [0, 1].

    The Tabulator outputs a geometrically valid cuboid (or two-box) whatever it is
    shown, so when that silhouette explains the input well, the model's shape class
    fits the building. A box forced onto a two-box building must leave one wing
    uncovered or overhang the notch between them, and the IoU drops; a heavily
    occluded or non-cuboid mask lowers it as well. The target is the input, not
    each model's refined mask: each Refiner pulls the mask towards its own class,
    so judging a model against its own refinement flatters it (on 240 mixed
    samples, choosing by the refined masks was right 80% of the time, by the input 86%).
    """
    target = np.asarray(mask.detach().cpu() if hasattr(mask, "detach") else mask)  # a torch row, or an array
    return coverage(shape, keypoints, target.reshape(target.shape[-2:]) > 0)[0]  # a batch row (1, S, S) or (H, W)


def coverage(shape: str | Shape, keypoints: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """The fitted silhouette's IoU with a bool (H, W) `mask` (`confidence`), and the share of the mask's
    pixels it leaves out (`cuboidtrain.fit.trust`'s unexplained share): one rasterisation for both."""
    fitted = model_silhouette(shape, keypoints, mask.shape)
    # count_nonzero: a bool mask's counts at a fifth of a sum's cost
    both, union = np.count_nonzero(np.logical_and(fitted, mask)), np.count_nonzero(np.logical_or(fitted, mask))
    total = np.count_nonzero(mask)
    return (float(both / union) if union else 0.0), float((total - both) / max(total, 1))


def extent_px(mask: np.ndarray) -> float:
    """A silhouette's size: its bounding box's longer side in px (at least 1): what a mask shows of
    a building's corners (`uncertainty.inflation`, `cuboidtrain.fit.trust`)."""
    rows, columns = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return 1.0
    return float(max(rows[-1] - rows[0] + 1, columns[-1] - columns[0] + 1))


def roof_notches(mask: np.ndarray, depth: float, size: float | None = None) -> int:
    """How many notches open down from the top of the silhouette's outline deeper than `depth` (a share
    of its size, `extent_px`): `top_notches`. A projected box's silhouette is convex; a twobox's
    shows at most one, where the lower box meets the taller; a row of houses shows one between each
    two roofs. An occluder standing in front (a tree, a person, a sign) cuts its notch from the bottom
    or the side, which this does not count. `size`: the silhouette's `extent_px`, where the caller has it."""
    size = extent_px(mask) if size is None else size
    return int(np.count_nonzero(top_notches(mask) > depth * size * 256))  # OpenCV's depths are fixed point, 8 bits


def top_notches(mask: np.ndarray) -> np.ndarray:
    """The depths (px in OpenCV's fixed point: 8 fractional bits) of the convexity defects of the silhouette's
    largest outline that open down from its top: the hull edge over the notch runs more across than up and
    down, and the notch lies below it. Empty where there are none."""
    outlines, _ = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(outlines, key=cv2.contourArea) if outlines else np.zeros((0, 1, 2), np.int32)
    if len(outline) < 4:
        return np.zeros(0)
    hull = np.sort(cv2.convexHull(outline, returnPoints=False), axis=0)  # sorted: OpenCV asks monotone indices
    defects = cv2.convexityDefects(outline, hull)
    if defects is None:
        return np.zeros(0)
    start, end, far, deep = defects.reshape(-1, 4).T
    points = outline[:, 0].astype(np.int64)
    (x0, y0), (x1, y1), y = points[start].T, points[end].T, points[far, 1]
    return deep[(np.abs(x1 - x0) > np.abs(y1 - y0)) & (y > (y0 + y1) / 2)]
