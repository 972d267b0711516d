"""A fitted cuboid's silhouette and how well it explains a mask (IoU), drawn by the generator's rasteriser."""
from __future__ import annotations

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
    target = target.reshape(target.shape[-2:]) > 0  # a batch row (1, S, S) or an image (H, W)
    fitted = model_silhouette(shape, keypoints, target.shape)
    union = np.logical_or(fitted, target).sum()
    return float(np.logical_and(fitted, target).sum() / union) if union else 0.0


def extent_px(mask: np.ndarray) -> float:
    """A silhouette's size: its bounding box's longer side in px (at least 1): what a mask shows of
    a building's corners (`uncertainty.inflation`, `cuboidtrain.fit.trust`)."""
    rows, columns = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return 1.0
    return float(max(rows[-1] - rows[0] + 1, columns[-1] - columns[0] + 1))
