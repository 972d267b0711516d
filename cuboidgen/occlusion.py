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


def occlude(mask: np.ndarray, library, scene: SceneConfig, rng: np.random.Generator) -> tuple[np.ndarray, list[dict]]:
    """A copy of `mask` with occluders removed from it, and what was placed."""
    out = mask.copy()
    if not len(library) or not mask.any():
        return out, []
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    box = (float(cols[0]), float(rows[0]), float(cols[-1]), float(rows[-1]))  # x0, y0, x1, y1
    placed = []
    count = int(rng.integers(scene.occluders[0], scene.occluders[1] + 1))
    for _ in range(count):
        placement = draw_placement(library, box, scene, rng)
        subtract(out, library.masks[placement["index"]], placement)
        placed.append(placement)
    return out, placed


def draw_placement(library, box: tuple[float, float, float, float], scene: SceneConfig, rng) -> dict:
    x0, y0, x1, y1 = box
    height = y1 - y0 + 1
    index = int(rng.integers(len(library)))
    target = height * (scene.occluder_height[0] + (scene.occluder_height[1] - scene.occluder_height[0]) * rng.random())
    grounded = bool(rng.random() < scene.grounded_probability)
    # A grounded occluder's foot lands near the building's ground line; others anywhere over it.
    foot_y = y1 + height * 0.05 * (rng.random() - 0.3) if grounded else y0 + (y1 - y0 + target) * rng.random()
    return {
        "index": index,
        "kind": library.names[index],
        "height_px": float(target),
        "angle_deg": float(scene.occluder_rotation_deg[0] + np.ptp(scene.occluder_rotation_deg) * rng.random()),
        "flip": bool(rng.random() < 0.5),
        "x": float(x0 + (x1 - x0) * rng.random()),
        "foot_y": float(foot_y),
        "grounded": grounded,
    }


def placement_matrix(shape: tuple[int, int], p: dict) -> np.ndarray:
    """2x3 affine from cutout pixels to image pixels: foot (bottom centre) to (x, foot_y)."""
    h, w = shape
    s = p["height_px"] / h
    a = math.radians(p["angle_deg"])
    sx = -s if p["flip"] else s
    linear = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ np.diag([sx, s])
    foot = np.array([(w - 1) / 2, h - 1])
    offset = np.array([p["x"], p["foot_y"]]) - linear @ foot
    return np.hstack([linear, offset[:, None]])


def subtract(mask: np.ndarray, cutout: np.ndarray, p: dict) -> None:
    """Clear the pixels of `mask` covered by the placed cutout, warping only its bounding box."""
    matrix = placement_matrix(cutout.shape, p)
    h, w = cutout.shape
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1]]) @ matrix.T
    left, top = np.maximum(np.floor(corners.min(axis=0)).astype(int), 0)
    right, bottom = np.minimum(np.ceil(corners.max(axis=0)).astype(int), (mask.shape[1] - 1, mask.shape[0] - 1))
    if right < left or bottom < top:
        return
    matrix[:, 2] -= (left, top)  # warp into the region of interest only
    warped = cv2.warpAffine(cutout, matrix, (int(right - left + 1), int(bottom - top + 1)), flags=cv2.INTER_NEAREST)
    mask[top : bottom + 1, left : right + 1] &= warped == 0
