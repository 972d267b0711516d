"""Fit a cuboid to a binary mask at the input's own resolution: the outline's residuals
(how far the mask's outline lies from the model's silhouette and back), a pull toward the
networks' corners by confidence, and `cuboidtrain.fit.lift`'s solver.

Measured (docs/research/geometric-fit/RESULTS.md, 3a/3b): from true corners + 3 px
noise on clean masks, hull corners to a median 0.4-0.5 px; from the shipped networks'
corners, clean-mask medians improve strongly (box 2.8 -> 0.7 px) while noisy means barely
move; about 55 ms a shape with forward-difference Jacobians.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cuboidtrain.fit.geometry import CameraParams, CuboidFit, describe, project, ratios
from cuboidtrain.fit.lift import levenberg_marquardt, lift
from shared.raster import rasterize
from shared.shapes import Shape

@dataclass(frozen=True)
class MaskFitWeights:
    """Residual weights (per px of distance). Mask pixels outside the model cost the most:
    occluders only remove pixels, so a building pixel the model leaves out is a real miss,
    while model outline over background may be an occluded part (robust, bounded cost)."""

    outside: float = 1.0  # mask boundary point outside the model
    inside: float = 0.5  # mask boundary point inside the model (occlusion-tolerant, robust)
    overhang: float = 0.5  # model outline over background (occlusion-tolerant, robust)
    robust_px: float = 3.0  # scale of the Cauchy-like saturation of the tolerant terms
    corners: float = 0.15  # pull of a confidence-1 network corner, per px
    ratios: float = 0.3  # pull of log depth/height and log width/height toward the network's head
    samples_per_edge: int = 4
    max_boundary_points: int = 120


def boundary_points(mask: np.ndarray, limit: int) -> np.ndarray:
    """(M, 2) points on the mask's outline: the midpoints between 4-neighbouring pixel centres
    of which one is in and one out. Under the pixel-centre rule the true outline crosses each
    such crack within half a pixel, unbiased, unlike contour pixel centres (0.5 px inside)."""
    m = mask.astype(bool)
    ys, xs = np.nonzero(m[:, :-1] != m[:, 1:])
    horizontal = np.stack([xs + 0.5, ys], axis=1)
    ys, xs = np.nonzero(m[:-1] != m[1:])
    vertical = np.stack([xs, ys + 0.5], axis=1)
    points = np.concatenate([horizontal, vertical]).astype(np.float64)
    if len(points) > limit:
        points = points[np.linspace(0, len(points) - 1, limit).astype(int)]
    return points


def signed_distance_field(mask: np.ndarray) -> np.ndarray:
    """Approximate distance to the mask's outline in px, positive outside the mask."""
    m = mask.astype(np.uint8)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(m > 0, 0.5 - inside, outside - 0.5).astype(np.float64)


def bilinear(field: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`field` sampled at (..., 2) x, y points, clamped at the border."""
    h, w = field.shape
    points = np.nan_to_num(points, nan=-1.0)  # a diverged trial step: costed, then rejected by LM
    x = np.clip(points[..., 0], 0, w - 1.001)
    y = np.clip(points[..., 1], 0, h - 1.001)
    x0, y0 = x.astype(int), y.astype(int)
    fx, fy = x - x0, y - y0
    top = field[y0, x0] * (1 - fx) + field[y0, x0 + 1] * fx
    bottom = field[y0 + 1, x0] * (1 - fx) + field[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


_PAIRS = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)])  # 28 candidate hull edges


def hull_edges(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For (B, 8, 2) corners of convex parts: every corner pair's start (B, 28, 2), direction
    (B, 28, 2), outward unit normal (B, 28, 2), and whether it is a hull edge (B, 28): all the
    other corners lie on its inner side. Vectorised: no per-hypothesis convexHull call."""
    a, b = corners[:, _PAIRS[:, 0]], corners[:, _PAIRS[:, 1]]
    direction = b - a
    normal = np.stack([direction[..., 1], -direction[..., 0]], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True) + 1e-12
    side = np.einsum("bkd,bnd->bkn", normal, corners) - np.einsum("bkd,bkd->bk", normal, a)[..., None]
    flip = np.where(side.sum(-1) > 0, -1.0, 1.0)  # outward: away from the rest
    normal *= flip[..., None]
    side *= flip[..., None]
    is_edge = (side <= 1e-9 * (1 + np.abs(side).max(-1, keepdims=True))).all(-1)
    return a, direction, normal, is_edge


def polygon_distance(points: np.ndarray, a: np.ndarray, normal: np.ndarray, is_edge: np.ndarray) -> np.ndarray:
    """Signed distance (positive outside) of (B, M, 2) points to convex hulls given by their
    edges: the largest outward offset over hull edges (exact inside, a lower bound outside)."""
    offset = np.einsum("bmd,bkd->bmk", points, normal) - np.einsum("bkd,bkd->bk", a, normal)[:, None]
    return np.where(is_edge[:, None], offset, -np.inf).max(-1)


def _tolerant(d: np.ndarray, scale: float) -> np.ndarray:
    """A residual whose square is Cauchy's loss: linear near 0, log-growing past `scale`."""
    return np.sign(d) * scale * np.sqrt(np.log1p((d / scale) ** 2))


def silhouette_residuals(params: np.ndarray, mirrors: np.ndarray, shape: Shape, outline: np.ndarray,
                         sdf: np.ndarray, weights: MaskFitWeights) -> np.ndarray:
    """(B, M) residuals of how well each hypothesis' silhouette explains the mask."""
    image = project(params, shape, mirrors)
    parts = [hull_edges(image[:, list(p)]) for p in shape.parts]
    pts = np.broadcast_to(outline, (len(params), *outline.shape))
    dist = np.min([polygon_distance(pts, a, n, e) for a, _, n, e in parts], axis=0)
    out = np.where(dist > 0, weights.outside * dist, weights.inside * _tolerant(dist, weights.robust_px))
    t = (np.arange(weights.samples_per_edge) + 0.5) / weights.samples_per_edge
    residuals = [out]
    for k, (a, direction, _, is_edge) in enumerate(parts):
        samples = a[:, :, None] + direction[:, :, None] * t[:, None]  # (B, 28, T, 2)
        flat = samples.reshape(len(params), -1, 2)
        keep = np.repeat(is_edge, len(t), axis=1)
        for j, (a2, _, n2, e2) in enumerate(parts):  # a twobox outline inside the other part is no outline
            if j != k:
                keep &= polygon_distance(flat, a2, n2, e2) > 0
        over = bilinear(sdf, flat)
        over = np.where(over > 0, weights.overhang * _tolerant(over, weights.robust_px), weights.outside * over)
        # Scale by edge length: each outline px counts once, whatever the edge's sample count.
        length = np.repeat(np.linalg.norm(direction, axis=-1), len(t), axis=1) / len(t)
        residuals.append(np.where(keep, over * np.sqrt(length), 0.0))
    return np.concatenate(residuals, axis=1)


def fit_mask(mask: np.ndarray, shape: Shape, corners: np.ndarray, confidence: np.ndarray,
             prior_ratios: np.ndarray | None = None, weights: MaskFitWeights = MaskFitWeights(),
             starts: int = 2, iterations: int = 20) -> CuboidFit:
    """Cuboid params that explain a binary mask (input resolution), started from the lift of the
    network corners (the `starts` best lift hypotheses) and pulled toward them by confidence.
    `prior_ratios` (the network's ratio head, `shape.ratio_names` order) anchors the extents the
    outline leaves free: near-frontal views trade depth against yaw and focal length (RESULTS.md)."""
    lifted = lift(corners, shape, confidence, k_starts=(0.0, 0.3), iterations=15, tolerance=1e-9, polish=0)
    order = np.argsort(lifted.costs)[:starts]
    x0, mirrors = lifted.hypotheses[order], lifted.mirrors[order]
    outline = boundary_points(mask, weights.max_boundary_points)
    sdf = signed_distance_field(mask)
    # Boundary terms are normalised so the corner pull means the same whatever the outline length.
    norm = 1 / np.sqrt(len(outline))
    pull = weights.corners * np.sqrt(np.clip(confidence, 0.05, 1.0))[None, :, None]

    def residual(x, rows):
        fit = silhouette_residuals(x, mirrors[rows], shape, outline, sdf, weights) * norm
        prior = ((project(x, shape, mirrors[rows]) - corners) * pull).reshape(len(x), -1) * norm
        extents = weights.ratios * np.log(ratios(x, shape) / prior_ratios) if prior_ratios is not None else fit[:, :0]
        return np.concatenate([fit, prior, extents], axis=1)

    solved = levenberg_marquardt(residual, x0, iterations, step=1e-6, tolerance=1e-7)
    best = int(np.argmin(solved.cost))
    camera = CameraParams(shape, solved.params[best], bool(mirrors[best]))
    outline_rms = float(np.sqrt(np.mean(silhouette_residuals(solved.params[best : best + 1], mirrors[best : best + 1],
                                                                shape, outline, sdf, weights)[0] ** 2)))
    return describe(camera, outline_rms, iou=agreement(mask, shape, camera)[0])


def agreement(mask: np.ndarray, shape: Shape, camera: CameraParams) -> tuple[float, float]:
    """IoU of the camera's silhouette with the mask, and the share of mask pixels it misses."""
    height, width = mask.shape
    model = rasterize(shape, camera.keypoints(), max(height, width))[:height, :width]  # rasterize draws squares
    m = mask.astype(bool)
    inter = np.logical_and(model, m).sum()
    return float(inter / max(np.logical_or(model, m).sum(), 1)), float(1 - inter / max(m.sum(), 1))
