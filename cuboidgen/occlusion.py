"""Occlusion: subtract random urban occluders from a silhouette (paper 3.3.1, Figure 15).

Each occluder is a cutout from an `OccluderLibrary`, given a random height
(relative to the silhouette's), a flip, a rotation and a position. Street
occluders stand on the ground, so most are placed on the building's ground line.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from cuboidgen.config import SceneConfig

Box = tuple[float, float, float, float]  # x0, y0, x1, y1: pixel centres, inclusive


def occlude(
    mask: np.ndarray, library, scene: SceneConfig, rng: np.random.Generator, box: Box | None = None
) -> tuple[np.ndarray, list[dict]]:
    """A copy of `mask` with occluders removed from it, and what was placed.

    `box` is the silhouette's bounding box when the caller knows it (from the
    keypoints); otherwise it is measured on the mask.
    """
    out = mask.copy()
    if box is None:
        box = bounding_box(mask)
    if not len(library) or box is None:
        return out, []
    placed = []
    count = int(rng.integers(scene.occluders[0], scene.occluders[1] + 1))
    keep = keep_masks(library) if count else None
    for _ in range(count):
        placement = draw_placement(library, box, scene, rng)
        _clear(out, keep[placement["index"]], placement, box)
        placed.append(placement)
    return out, placed


def keep_masks(library) -> list[np.ndarray]:
    """Each cutout inverted (1 off the occluder, 0 on it), made once per library: warped
    with 1 outside the cutout, it is the mask of pixels that stay, ready to AND in."""
    cached = getattr(library, "_keep_masks", None)
    if cached is None or cached[0] is not library.masks or len(cached[1]) != len(library.masks):
        cached = library.masks, [np.ascontiguousarray(m == 0, dtype=np.uint8) for m in library.masks]
        library._keep_masks = cached
    return cached[1]


def bounding_box(mask: np.ndarray) -> Box | None:
    """The bounding box of a mask's set pixels, or None for an empty mask."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return float(cols[0]), float(rows[0]), float(cols[-1]), float(rows[-1])


def draw_placement(library, box: Box, scene: SceneConfig, rng) -> dict:
    x0, y0, x1, y1 = box
    height = y1 - y0 + 1
    index = int(rng.integers(len(library)))
    # One call for the six draws: the same numbers as one `rng.random()` each, in this order.
    size, ground, foot, angle, flip, across = rng.random(6).tolist()
    (h_lo, h_hi), (a_lo, a_hi) = scene.occluder_height, scene.occluder_rotation_deg
    target = height * (h_lo + (h_hi - h_lo) * size)
    grounded = ground < scene.grounded_probability
    # A grounded occluder's foot lands near the building's ground line; others anywhere over it.
    foot_y = y1 + height * 0.05 * (foot - 0.3) if grounded else y0 + (y1 - y0 + target) * foot
    return {
        "index": index,
        "kind": library.names[index],
        "height_px": float(target),
        "angle_deg": float(a_lo + (a_hi - a_lo) * angle),
        "flip": flip < 0.5,
        "x": float(x0 + (x1 - x0) * across),
        "foot_y": float(foot_y),
        "grounded": grounded,
    }


def placement_affine(shape: tuple[int, int], p: dict) -> tuple[float, float, float, float, float, float]:
    """(a, b, tx, c, d, ty): the affine from cutout pixels to image pixels, mapping the
    foot (bottom centre) to (x, foot_y). Plain floats: numpy costs more on six numbers."""
    h, w = shape
    s = p["height_px"] / h
    sx = -s if p["flip"] else s
    cos, sin = math.cos(math.radians(p["angle_deg"])), math.sin(math.radians(p["angle_deg"]))
    a, b, c, d = cos * sx, -sin * s, sin * sx, cos * s  # rotation @ diag(sx, s)
    foot_x, foot_y = (w - 1) / 2, h - 1
    return a, b, p["x"] - a * foot_x - b * foot_y, c, d, p["foot_y"] - c * foot_x - d * foot_y


def subtract(mask: np.ndarray, cutout: np.ndarray, p: dict, limit: Box | None = None) -> None:
    """Clear the pixels of `mask` covered by the placed cutout, warping only the part of
    its bounding box inside the image (and inside `limit`, beyond which `mask` is known
    to be empty)."""
    _clear(mask, np.ascontiguousarray(cutout == 0, dtype=np.uint8), p, limit)


def _clear(mask: np.ndarray, keep: np.ndarray, p: dict, limit: Box | None) -> None:
    """`subtract` with the cutout given inverted (`keep_masks`): one warp and one AND."""
    a, b, tx, c, d, ty = placement_affine(keep.shape, p)
    h, w = keep.shape
    corners = [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)]
    xs = [a * u + b * v + tx for u, v in corners]
    ys = [c * u + d * v + ty for u, v in corners]
    x0, y0, x1, y1 = limit if limit is not None else (0, 0, mask.shape[1] - 1, mask.shape[0] - 1)
    left, top = max(math.floor(min(xs)), int(x0), 0), max(math.floor(min(ys)), int(y0), 0)
    right = min(math.ceil(max(xs)), int(x1), mask.shape[1] - 1)
    bottom = min(math.ceil(max(ys)), int(y1), mask.shape[0] - 1)
    if right < left or bottom < top:
        return
    matrix = np.array([[a, b, tx - left], [c, d, ty - top]])  # warp into the region of interest only
    kept = cv2.warpAffine(
        keep, matrix, (right - left + 1, bottom - top + 1), flags=cv2.INTER_NEAREST, borderValue=1
    )
    region = mask[top : bottom + 1, left : right + 1]
    np.bitwise_and(region, kept.view(bool), out=region)
