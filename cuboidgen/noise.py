"""Contour noise: roughen a silhouette's boundary the way segmentation networks do.

Every boundary (outer and holes) is displaced along its normal by a smooth random
signal whose standard deviation is the noise amount in px and whose correlation
length along the contour is the wavelength, plus a little per-pixel jitter.

All contours are processed together, concatenated into one point array, so the
cost is a fixed handful of numpy calls per sample rather than per contour.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

SHIFT = 4  # fixed-point bits for sub-pixel polygon vertices
JITTER = 0.15  # per-pixel jitter as a fraction of the amount


def roughen(mask: np.ndarray, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """`mask` with its boundaries displaced by about `amount` px (std); 0 returns a copy."""
    if amount <= 0 or not mask.any():
        return mask.copy()
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    lengths = np.array([len(c) for c in contours])
    # x and y as separate 1-D arrays: numpy is many times slower on (N, 2) arrays
    # (axis reductions, row gathers, broadcasting a pair) than on two flat ones.
    points = np.concatenate(contours).reshape(-1, 2)
    xs, ys = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    nx, ny = _normals(xs, ys, lengths)
    signal = _signals(lengths, amount, wavelength, rng)
    xs += nx * signal
    ys += ny * signal
    return _fill(xs, ys, lengths, mask.shape)


def _fill(xs: np.ndarray, ys: np.ndarray, lengths: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A mask of the closed polygons (x, y concatenated, `lengths` points each), filled
    even-odd so holes stay open. Boundary pixel centres refilled without noise give
    back the original mask exactly."""
    out = np.zeros(shape, np.uint8)
    # Fill only the box the polygons reach: integer shifts leave the fill unchanged.
    left, top = max(math.floor(xs.min()), 0), max(math.floor(ys.min()), 0)
    right, bottom = min(math.ceil(xs.max()), shape[1] - 1), min(math.ceil(ys.max()), shape[0] - 1)
    if right < left or bottom < top:
        return out.view(bool)
    fixed = np.empty((len(xs), 2))
    fixed[:, 0], fixed[:, 1] = xs - left, ys - top
    fixed = np.rint(fixed * (1 << SHIFT)).astype(np.int32)
    ends = np.cumsum(lengths).tolist()
    polygons = [fixed[end - n : end] for end, n in zip(ends, lengths.tolist())]
    cv2.fillPoly(out[top : bottom + 1, left : right + 1], polygons, 1, shift=SHIFT)
    return out.view(bool)


def _normals(xs: np.ndarray, ys: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of concatenated closed contours, from each point's two neighbours
    on its own contour. Contours of one or two points get zero normals (no noise)."""
    ends = np.cumsum(lengths) - 1
    starts = ends - lengths + 1
    index = np.arange(len(xs))
    after, before = index + 1, index - 1
    after[ends], before[starts] = starts, ends  # each contour wraps onto itself
    dx, dy = xs.take(after) - xs.take(before), ys.take(after) - ys.take(before)
    norm = np.maximum(np.hypot(dx, dy), 1e-9)
    return np.divide(dy, norm, out=dy), np.divide(dx, -norm, out=dx)


def _signals(lengths: np.ndarray, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """A periodic random signal along each contour: knots every `wavelength` points,
    linearly interpolated, plus jitter; its standard deviation is about `amount`.
    Each contour's knots occupy their own block of one knot array, so one
    interpolation serves all contours."""
    knots = np.maximum((lengths / max(wavelength, 1.0)).astype(int), 3)
    block_end = np.cumsum(knots + 1)
    block_start = block_end - knots - 1
    values = rng.normal(0.0, amount, int(block_end[-1]))
    values[block_end - 1] = values[block_start]  # closes each loop
    # Position along the contour in knot units, offset into the contour's own block.
    first_point = np.cumsum(lengths) - lengths
    step = np.arange(int(lengths.sum())) - np.repeat(first_point, lengths)
    position = np.repeat(block_start, lengths) + step * np.repeat(knots / lengths, lengths)
    signal = np.interp(position, np.arange(len(values)), values)
    # Linear interpolation between independent knots keeps two thirds of the variance.
    return signal * 1.22 + rng.normal(0.0, amount * JITTER, len(step))

