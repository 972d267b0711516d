"""Contour noise: roughen a silhouette's boundary the way segmentation networks do.

Every boundary (outer and holes) is displaced along its normal by a smooth random
signal whose standard deviation is the noise amount in px and whose correlation
length along the contour is the wavelength, plus a little per-pixel jitter.
"""
from __future__ import annotations

import cv2
import numpy as np

SHIFT = 4  # fixed-point bits for sub-pixel polygon vertices
JITTER = 0.15  # per-pixel jitter as a fraction of the amount


def roughen(mask: np.ndarray, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """`mask` with its boundaries displaced by about `amount` px (std); 0 returns a copy."""
    if amount <= 0 or not mask.any():
        return mask.copy()
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    displaced = [_displace(c[:, 0, :].astype(np.float64), amount, wavelength, rng) for c in contours]
    out = np.zeros(mask.shape, np.uint8)
    # Boundary pixel centres refilled without noise give back the mask exactly, and the
    # even-odd fill keeps holes open.
    cv2.fillPoly(out, [np.round(d * (1 << SHIFT)).astype(np.int32) for d in displaced], 1, shift=SHIFT)
    return out.view(bool)


def _displace(points: np.ndarray, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    n = len(points)
    if n < 3:
        return points
    wrapped = np.concatenate([points[-1:], points, points[:1]])
    tangent = wrapped[2:] - wrapped[:-2]
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    normal /= np.maximum(np.hypot(normal[:, 0], normal[:, 1]), 1e-9)[:, None]
    return points + normal * smooth_signal(n, amount, wavelength, rng)[:, None]


def smooth_signal(n: int, amount: float, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """A periodic random signal of length n: knots every `wavelength` samples, linearly
    interpolated, plus jitter; its standard deviation is about `amount`."""
    knots = max(int(n / max(wavelength, 1.0)), 3)
    values = rng.normal(0.0, amount, knots + 1)
    values[-1] = values[0]  # closes the loop
    signal = np.interp(np.arange(n) * (knots / n), np.arange(knots + 1), values)
    # Linear interpolation between independent knots keeps two thirds of the variance.
    return signal * 1.22 + rng.normal(0.0, amount * JITTER, n)
