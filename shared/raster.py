"""Rasterisation of silhouettes under the pixel-centre rule: the silhouette of a shape is part of the
shape convention, so the generator draws training masks and inference scores fits with this one module.

A pixel belongs to a part when its centre lies inside (or on) the part's convex
hull; integer coordinates are pixel centres (docs/contract.md, "Coordinates: pixel centres"). OpenCV's polygon fill
covers every pixel an edge touches, which biases masks outward by up to a pixel,
so spans are computed here exactly and filled with vectorised comparisons.
"""
from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from shared.shapes import Shape


def fill_convex(mask: np.ndarray, points: np.ndarray) -> None:
    """Set the pixels of `mask` whose centres lie in the convex hull of `points`."""
    points = np.asarray(points, dtype=np.float64)
    index = cv2.convexHull(points.astype(np.float32), returnPoints=False).ravel().tolist()
    if len(index) < 3:
        return
    # A handful of vertices: Python floats and lists beat numpy calls here.
    coords = points.tolist()
    xs, ys = [coords[i][0] for i in index], [coords[i][1] for i in index]
    height, width = mask.shape
    top = max(math.ceil(min(ys)), 0)
    bottom = min(math.floor(max(ys)), height - 1)
    if bottom < top:
        return
    left, right = _spans(xs, ys, _row_centres(height)[top : bottom + 1])
    first = np.ceil(left, out=left).astype(np.intp)  # first column inside
    after = np.floor(right, out=right).astype(np.intp)
    after += 1  # first column past it
    from_first, before_after = _row_tables(width)
    # mode="clip" keeps spans that leave the image at its edges (columns 0 and width).
    rows = np.take(from_first, first, axis=0, mode="clip")
    rows &= np.take(before_after, after, axis=0, mode="clip")
    mask[top : bottom + 1] |= rows


@functools.cache
def _row_tables(width: int) -> tuple[np.ndarray, np.ndarray]:
    """Row k of the first table is `col >= k`, of the second `col < k`: a span is then
    two row gathers and an AND, several times faster than comparing every pixel."""
    cols, k = np.arange(width)[None, :], np.arange(width + 1)[:, None]
    return cols >= k, cols < k


@functools.cache
def _row_centres(height: int) -> np.ndarray:
    return np.arange(height, dtype=np.float64)


def _spans(xs: list[float], ys: list[float], rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leftmost and rightmost x of a convex polygon (vertices `xs`, `ys` in hull order)
    on each row centre.

    The hull splits at its top and bottom vertices into two chains that are
    monotonic in y, so each chain's x at every row is one linear interpolation.
    """
    n = len(ys)
    top, bottom = ys.index(min(ys)), ys.index(max(ys))
    one_way = [(top + k) % n for k in range((bottom - top) % n + 1)]
    other_way = [(top - k) % n for k in range((top - bottom) % n + 1)]
    xa = np.interp(rows, np.array([ys[i] for i in one_way]), np.array([xs[i] for i in one_way]))
    xb = np.interp(rows, np.array([ys[i] for i in other_way]), np.array([xs[i] for i in other_way]))
    return np.minimum(xa, xb), np.maximum(xa, xb, out=xb)


def rasterize(shape: Shape, keypoints: np.ndarray, size: int) -> np.ndarray:
    """The clean silhouette: the union of the parts' convex hulls, as a bool mask."""
    mask = np.zeros((size, size), dtype=bool)
    for part in shape.parts:
        fill_convex(mask, keypoints[list(part)])
    return mask
