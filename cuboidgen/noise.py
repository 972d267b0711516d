"""Contour noise: roughen a silhouette's boundary the way segmentation networks do.

Every boundary (outer and holes) is displaced along its normal by a smooth random
signal whose standard deviation is the noise amount in px and whose correlation
length along the contour is the wavelength, plus a little per-pixel jitter.

All contours are processed together, concatenated into one point array, so the
cost is a fixed handful of numpy calls per sample (plus a few scalar operations
per contour) rather than a pass of array work per contour.
"""
from __future__ import annotations

import sys

import cv2
import numpy as np

SHIFT = 4  # fixed-point bits for sub-pixel polygon vertices
JITTER = 0.15  # per-pixel jitter as a fraction of the amount
KNOT_GAIN = 1.22  # linear interpolation between independent knots keeps two thirds of the variance

if sys.byteorder != "little":  # roughen reads a point's int32 (x, y) pair as one int64
    raise ImportError("cuboidgen.noise assumes a little-endian machine")


def roughen(mask: np.ndarray, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """`mask` with its boundaries displaced by about `amount` px (std); 0 returns a copy."""
    if amount <= 0:
        return mask.copy()
    # RETR_LIST: every outer boundary and hole, without the hierarchy (unused; 30% dearer).
    # Tracing only the silhouette's bounding box was measured no faster: the cost is in
    # following the contours, not in scanning the image.
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:  # an empty mask
        return mask.copy()
    lengths = [len(c) for c in contours]
    # (N, 2) int32 points, x then y; viewed as one int64 per point (x + y * 2**32 on a
    # little-endian machine, x >= 0) so differences of points are one flat subtraction.
    points = contours[0].reshape(-1, 2) if len(contours) == 1 else np.concatenate(contours).reshape(-1, 2)
    normals = contour_normals(points.view(np.int64).ravel(), lengths)
    normals *= _signals(lengths, amount * (1 << SHIFT), wavelength, rng)  # displacement, fixed point
    offsets = normals.view(np.float64)  # x, y interleaved, in 1/16 px
    np.rint(offsets, out=offsets)
    fixed = offsets.astype(np.int32).reshape(-1, 2)
    fixed += points << SHIFT
    return _fill(fixed, lengths, mask.shape)


def _fill(fixed: np.ndarray, lengths: list[int], shape: tuple[int, int]) -> np.ndarray:
    """A mask of the closed polygons (fixed-point vertices, `lengths` points each),
    filled even-odd so holes stay open. Boundary pixel centres refilled without noise
    give back the original mask exactly; parts outside the image are clipped."""
    out = np.zeros(shape, np.uint8)
    if len(lengths) == 1:
        polygons = [fixed]
    else:
        polygons, start = [], 0
        for n in lengths:
            polygons.append(fixed[start : start + n])
            start += n
    cv2.fillPoly(out, polygons, 1, shift=SHIFT)
    return out.view(bool)


# Unit normals of a contour point from the difference (dx, dy) between its two
# neighbours, both in [-2, 2] on an 8-connected contour. The difference arrives as
# dx + dy * 2**32 (one int64); modulo 27 maps the 25 possible pairs to distinct
# slots, so a normal is one table lookup. Zero for (0, 0): a contour of one or two
# points has no direction and gets no noise.
_NORMAL_MODULUS = 27


def _normal_table() -> np.ndarray:
    table = np.zeros(_NORMAL_MODULUS, np.complex128)  # x + i y
    for dx in range(-2, 3):
        for dy in range(-2, 3):
            if dx or dy:
                table[(dx + dy * 2**32) % _NORMAL_MODULUS] = complex(dy, -dx) / np.hypot(dx, dy)
    return table


_NORMALS = _normal_table()


def contour_normals(packed: np.ndarray, lengths: list[int]) -> np.ndarray:
    """Unit normals (x + i y, complex) of concatenated closed contours of `packed`
    points (x + y * 2**32), each from its two neighbours on its own contour."""
    step = np.empty(len(packed), np.int64)
    start = 0
    for n in lengths:
        end = start + n
        if n < 3:
            step[start:end] = 0
        else:
            np.subtract(packed[start + 2 : end], packed[start : end - 2], out=step[start + 1 : end - 1])
            step[start] = packed[start + 1] - packed[end - 1]  # each contour wraps onto itself
            step[end - 1] = packed[start] - packed[end - 2]
        start = end
    return _NORMALS.take(np.remainder(step, _NORMAL_MODULUS, out=step))


def _signals(lengths: list[int], amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """A periodic random signal along each contour: knots every `wavelength` points,
    linearly interpolated, plus jitter; its standard deviation is about `amount`.
    Each contour's knots occupy their own block of one knot array (its last knot
    repeats its first, closing the loop), so one interpolation serves all contours."""
    total = sum(lengths)
    step = max(wavelength, 1.0)
    knots = [max(int(n / step), 3) for n in lengths]
    count = sum(knots) + len(knots)  # k + 1 values per contour
    draws = rng.standard_normal(count + total)
    values, jitter = draws[:count], draws[count:]
    grid = _arange(max(count, total))
    if len(lengths) == 1:
        n, k = total, knots[0]
        values[k] = values[0]
        position = grid[:n] * (k / n)
    else:
        parts, block = [], 0
        for n, k in zip(lengths, knots):
            values[block + k] = values[block]
            parts.append(grid[:n] * (k / n) + block)
            block += k + 1
        position = np.concatenate(parts)
    signal = np.interp(position, grid[:count], values)
    signal *= amount * KNOT_GAIN
    jitter *= amount * JITTER
    signal += jitter
    return signal


_GRID = np.arange(4096, dtype=np.float64)


def _arange(n: int) -> np.ndarray:
    """0.0, 1.0, ... at least `n` long (a cached array: callers slice it)."""
    global _GRID
    if len(_GRID) < n:
        _GRID = np.arange(max(n, 2 * len(_GRID)), dtype=np.float64)
    return _GRID
