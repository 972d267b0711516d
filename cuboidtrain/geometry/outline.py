"""How well a cuboid's silhouette explains a binary mask, at the input's own resolution: the
outline's residuals (how far the mask's outline lies from the model's silhouette and back)
and their derivatives, and what they read of a mask (`MaskTarget`: its outline points and
signed distance field; several masks' at once for a batch of fits). `cuboidtrain.geometry.mask_fit`
minimises them.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from cuboidtrain.geometry.camera_params import stack_last
from cuboidtrain.geometry.edge_lines import cracks
from shared.shapes import Shape
from shared.threads import threads_held

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
    ratios: float = 1.0  # pull of log width/height toward the network's head (the outline mostly fixes it)
    # Pull of log depth/height: near-frontal views trade depth against focal length, so the
    # outline barely fixes it. Measured on 30 masks a set: 3 or 4 (width 1 or 0.5) brings the
    # depth/height median from 46% to 27-37% on `paper-clean`, near the networks' 24%, but
    # the corners pay (clean twobox 3.2 -> 5.4 px mean): kept at 1.
    depth_ratio: float = 1.0
    camera: float = 0.3  # the typical camera's pull (`intrinsics.PlausibleRows`), per sd: 30 masks a set, 0.1-1 tried: 0.3 best on paper d/h (BENCHMARKS.md)
    samples_per_edge: int = 4
    max_boundary_points: int = 120


def boundary_points(mask: np.ndarray, limit: int, every: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(M, 2) points on the mask's outline, at most `limit` of them, evenly taken: the midpoints
    between 4-neighbouring pixel centres of which one is in and one out (`edge_lines.cracks`). Under
    the pixel-centre rule the true outline crosses each such crack within half a pixel, unbiased,
    unlike contour pixel centres (0.5 px inside). `every`: the mask's `cracks`, where the caller has them."""
    points = (cracks(mask) if every is None else every)[0]
    if len(points) > limit:
        points = points[np.linspace(0, len(points) - 1, limit).astype(int)]
    return points


# OpenCV's precise distance transform on one thread (a 1-core machine, or cv2.setNumThreads(1))
# differs from itself by up to 4e-6 px from call to call, and from its answer on two threads;
# on two threads or more it gives one answer, the same for any count (OpenCV 5.0.0,
# tests/test_geometry.py). The fit's flat valleys turn such bits into moves a user sees
# (BENCHMARKS.md, "The same answer everywhere"), so it always runs on two. OpenCV's count is the
# process's: the lock keeps threads that fit at once (a Dask worker's) from restoring it under
# each other.
DISTANCE_THREADS = 2
_DISTANCE_LOCK = threading.Lock()


def signed_distance_field(mask: np.ndarray) -> np.ndarray:
    """Approximate distance to the mask's outline in px, positive outside the mask."""
    m = mask.astype(np.uint8)
    with _DISTANCE_LOCK, threads_held(cv2.getNumThreads, cv2.setNumThreads, DISTANCE_THREADS):
        outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(m > 0, 0.5 - inside, outside - 0.5).astype(np.float64)


@dataclass(frozen=True)
class Fields:
    """Distance fields, one or several masks' (a batch of fits), sampled as one: their values
    one after another (`flat`), and where each point's field starts and its size, as scalars
    (one field) or arrays that broadcast against the points' leading axes (one per row)."""

    flat: np.ndarray
    offset: np.ndarray | int
    height: np.ndarray | int
    width: np.ndarray | int

    @classmethod
    def of(cls, field: np.ndarray | Fields) -> Fields:
        if isinstance(field, Fields):
            return field
        return cls(field.ravel(), 0, *field.shape)

    @classmethod
    def stacked(cls, fields: Sequence[np.ndarray]) -> Fields:
        """Several (H_k, W_k) fields; `rows` picks each row's."""
        sizes = np.array([f.size for f in fields])
        flat = fields[0].ravel() if len(fields) == 1 else np.concatenate([f.ravel() for f in fields])  # one: no copy
        return cls(flat, np.concatenate([[0], np.cumsum(sizes)[:-1]]),
                   np.array([f.shape[0] for f in fields]), np.array([f.shape[1] for f in fields]))

    def rows(self, owner: np.ndarray) -> Fields:
        """The fields of rows whose masks are `owner` (B,), indices into `stacked`'s list."""
        return Fields(self.flat, self.offset[owner], self.height[owner], self.width[owner])

    def broadcast(self, points: np.ndarray) -> tuple:
        """offset, height, width shaped to broadcast against (B, ..., 2) points' (B, ...)."""
        shape = (-1,) + (1,) * (points.ndim - 2)
        return tuple(v.reshape(shape) if isinstance(v, np.ndarray) and v.ndim else v
                     for v in (self.offset, self.height, self.width))


def bilinear(field: np.ndarray | Fields, points: np.ndarray) -> np.ndarray:
    """`field` sampled at (..., 2) x, y points, clamped at the border."""
    _, _, fx, fy, (tl, tr, bl, br) = _cell(Fields.of(field), np.fmax(points, -1.0))
    return (tl * (1 - fx) + tr * fx) * (1 - fy) + (bl * (1 - fx) + br * fx) * fy


def bilinear_with_gradient(field: np.ndarray | Fields, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`field` sampled at (..., 2) x, y points, clamped at the border, and its gradient (..., 2)
    (zero across a clamped coordinate)."""
    points = np.fmax(points, -1.0)
    x, y, fx, fy, (tl, tr, bl, br) = _cell(Fields.of(field), points)
    left_share, top_share = 1 - fx, 1 - fy
    top, bottom = tl * left_share + tr * fx, bl * left_share + br * fx
    gx = np.where(x == points[..., 0], (tr - tl) * top_share + (br - bl) * fy, 0.0)
    gy = np.where(y == points[..., 1], bottom - top, 0.0)
    return top * top_share + bottom * fy, stack_last([gx, gy])


def _cell(fields: Fields, points: np.ndarray):
    """The clamped x, y of (..., 2) points, their fractions in their pixel cell, and the
    field at the cell's four corners (top-left, top-right, bottom-left, bottom-right).
    Callers pass np.fmax(points, -1): a NaN of a diverged trial step becomes -1, clamped to
    the border like any point off the field (costed, then rejected by LM)."""
    offset, h, w = fields.broadcast(points)
    x = np.minimum(np.maximum(points[..., 0], 0), w - 1.001)  # np.clip's wrapper costs more than the two
    y = np.minimum(np.maximum(points[..., 1], 0), h - 1.001)
    x0, y0 = x.astype(np.intp), y.astype(np.intp)
    flat = fields.flat
    at = y0 * w + x0 + offset  # one flat index for the four corners: cheaper than four 2D lookups
    return x, y, x - x0, y - y0, (flat[at], flat[at + 1], flat[at + w], flat[at + w + 1])


_PAIRS = np.array([(i, j) for i in range(8) for j in range(i + 1, 8)])  # 28 candidate hull edges
_PAIR_STARTS, _PAIR_ENDS = _PAIRS[:, 0].copy(), _PAIRS[:, 1].copy()
QUARTER_TURN = np.array([[0.0, 1.0], [-1.0, 0.0]])  # (x, y) -> (y, -x)


# A convex part's silhouette has at most 6 edges; a degenerate view (coincident corners)
# can flag a few more pairs as edges, and those slots keep them.
HULL_SLOTS = 8


@dataclass(frozen=True)
class HullEdges:
    """The hull edges of (..., 8, 2) convex parts, HULL_SLOTS a part (unused slots invalid)."""

    start: np.ndarray  # (..., E, 2)
    direction: np.ndarray  # (..., E, 2) end - start
    normal: np.ndarray  # (..., E, 2) outward unit normal
    valid: np.ndarray  # (..., E) a real hull edge: all the other corners lie on its inner side
    pairs: np.ndarray  # (..., E, 2) the part's corner indices (0-7) at its start and end

    def swapped(self) -> HullEdges:
        """The hulls of (B, 2, ...) two-part shapes with the parts exchanged: each part's other."""
        return HullEdges(*(v[:, ::-1] for v in (self.start, self.direction, self.normal, self.valid, self.pairs)))


def hull_edges(corners: np.ndarray) -> HullEdges:
    """The hulls of (..., 8, 2) convex parts: every corner pair tested as an edge at once (no
    per-hypothesis convexHull call), then the edges packed into the first slots."""
    lead = corners.shape[:-2]
    corners = corners.reshape(-1, 8, 2)
    a, b = corners.take(_PAIR_STARTS, axis=1), corners.take(_PAIR_ENDS, axis=1)
    direction = b - a
    normal = direction @ QUARTER_TURN.T
    normal /= np.sqrt((normal * normal).sum(-1, keepdims=True)) + 1e-12
    side = normal @ corners.transpose(0, 2, 1) - (normal * a).sum(-1)[..., None]  # matmul: numpy's einsum costs more a call
    flip = np.where(side.sum(-1) > 0, -1.0, 1.0)  # outward: away from the rest
    normal *= flip[..., None]
    side *= flip[..., None]
    is_edge = (side <= 1e-9 * (1 + largest_over_edges(np.abs(side))[..., None])).all(-1)
    slots = np.argsort(~is_edge, axis=1, kind="stable")[:, :HULL_SLOTS]
    take = np.arange(0, len(corners) * len(_PAIRS), len(_PAIRS))[:, None] + slots  # one flat index: cheaper a call
    points, flags = (*lead, HULL_SLOTS, 2), (*lead, HULL_SLOTS)
    return HullEdges(a.reshape(-1, 2).take(take, axis=0).reshape(points),
                     direction.reshape(-1, 2).take(take, axis=0).reshape(points),
                     normal.reshape(-1, 2).take(take, axis=0).reshape(points), is_edge.reshape(-1)[take].reshape(flags),
                     _PAIRS.take(slots, axis=0).reshape(points))


def polygon_offsets(points: np.ndarray, hull: HullEdges) -> np.ndarray:
    """(..., M, E): the outward offset of (..., M, 2) points (or (M, 2), the same for every hull)
    from each hull edge's line; -inf for unused slots."""
    along = points @ np.swapaxes(hull.normal, -1, -2)
    offset = along - (hull.start * hull.normal).sum(-1)[..., None, :]
    return np.where(hull.valid[..., None, :], offset, -np.inf)


def polygon_distance(points: np.ndarray, hull: HullEdges) -> np.ndarray:
    """Signed distance (positive outside) of (..., M, 2) points to convex hulls given by their
    edges: the largest outward offset over hull edges (exact inside, a lower bound outside)."""
    return largest_over_edges(polygon_offsets(points, hull))


def largest_over_edges(offsets: np.ndarray) -> np.ndarray:
    """(...,) the largest of (..., E) offsets: read along contiguous rows of a transposed copy, several
    times faster than a reduction over a last axis of 8 (a maximum is exact: the same values)."""
    return np.ascontiguousarray(offsets.swapaxes(-1, -2)).max(-2)


def _offset_gradient(points: np.ndarray, start: np.ndarray, direction: np.ndarray, normal: np.ndarray,
                     length: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d/d start and d/d end (..., 2) of the offset (p - start).n of points p from the line
    through an edge, n its outward unit normal (n = +-quarter turn of the direction / length,
    (..., 1), `edge_lengths`' + 1e-12)."""
    tangent = direction / length
    # With p - a = alpha t + beta n (t the unit direction), n's turn with the edge gives
    # d o / d end = -alpha n / L, and the start moves the line as well: -n - that.
    along = ((points - start) * tangent).sum(-1, keepdims=True)
    d_end = -along * normal / length
    return -normal - d_end, d_end


def edge_lengths(hull: HullEdges) -> np.ndarray:
    """(..., E) each hull edge's length (np.linalg.norm's arithmetic, without its wrapper)."""
    return np.sqrt((hull.direction * hull.direction).sum(-1))


def _tolerant(d: np.ndarray, scale: float, slope: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """A residual whose square is Cauchy's loss: linear near 0, log-growing past `scale`; and, with
    `slope`, its derivative by d: 1 at 0, falling as the loss saturates (the root computed once for both)."""
    u = (d / scale) ** 2
    root = np.sqrt(np.log1p(u))
    value = np.sign(d) * scale * root
    if not slope:
        return value, None
    return value, np.where(u < 1e-12, 1.0, np.abs(d) / (scale * np.where(root > 0, root, 1.0) * (1 + u)))


def _weighted(d: np.ndarray, positive: float, negative: float, weights: MaskFitWeights, tolerant_when_positive: bool,
              derivatives: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """A distance's residual and, with `derivatives`, slope: one side linear at weight `outside`, the other robust."""
    tolerant, tolerant_slope = _tolerant(d, weights.robust_px, derivatives)
    above = d > 0
    if tolerant_when_positive:
        value = np.where(above, positive * tolerant, d if negative == 1.0 else negative * d)  # x 1: exact, no call
        slope = np.where(above, positive * tolerant_slope, negative) if derivatives else None
    else:
        value = np.where(above, d if positive == 1.0 else positive * d, negative * tolerant)
        slope = np.where(above, positive, negative * tolerant_slope) if derivatives else None
    return value, slope


def silhouette_terms(image: np.ndarray, shape: Shape, outline: np.ndarray, sdf: np.ndarray | Fields,
                     weights: MaskFitWeights, derivatives: bool = False,
                     valid: np.ndarray | None = None, deferred: bool = False) -> tuple[np.ndarray, object]:
    """(B, R) residuals of how well silhouettes with corners `image` (B, N, 2) explain the mask,
    and, if asked, their derivatives with respect to the corners (B, R, N, 2) (`deferred`: a function
    of no arguments that computes them from what the residuals left, for a solver that needs them
    only for the steps it takes: `lift.levenberg_marquardt`): each row
    touches the two corners of one edge (which edge is active is held fixed: the objective
    is piecewise smooth). One mask's `outline` (M, 2) and `sdf` (H, W), or each row's
    (a batch of masks): outline points (B, M, 2), padded where `valid` (B, M) is False (their
    rows are 0), and `Fields` sampled per row.

    Two kinds of rows: the mask's outline points' distance to the model's silhouette
    (positive outside: a missed building pixel, linear; inside: robust), and points along the
    model's outline edges sampled on the mask's signed distance field (over background:
    robust, an occluded part may be there; inside the mask: linear), each weighted by the
    square root of its share of the edge's length, so every outline px counts once.
    A twobox's two parts are one batch axis (B, P, ...): numpy's per-call cost, paid once."""
    b, n = image.shape[:2]
    parts = part_corners(shape)  # (P, 8) the shape's corner indices of each part
    hull = hull_edges(image.take(parts, axis=1))  # fields (B, P, E, ...)
    ends = parts.reshape(-1)[_part_starts(len(parts)) + hull.pairs]  # (B, P, E, 2) shape corner indices
    lengths = edge_lengths(hull)  # (B, P, E)
    outline_value, outline_gradient = _outline_rows(outline, valid, hull, ends, lengths, n, weights, derivatives)
    edge_value, edge_gradient = _edge_rows(hull, ends, lengths, Fields.of(sdf), n, weights, derivatives)
    residuals = np.concatenate([outline_value, edge_value], axis=1)
    if not derivatives:
        return residuals, None

    def gradient() -> np.ndarray:
        return np.concatenate([outline_gradient(), edge_gradient()], axis=1)

    return residuals, (gradient if deferred else gradient())


@lru_cache(maxsize=None)
def _part_starts(parts: int) -> np.ndarray:
    """(P, 1, 1): where each part's corner indices start in `part_corners(shape).reshape(-1)`."""
    starts = np.arange(0, 8 * parts, 8)[:, None, None]
    starts.flags.writeable = False  # shared by every caller
    return starts


@lru_cache(maxsize=None)
def part_corners(shape: Shape) -> np.ndarray:
    """(P, 8): the shape's corner indices of each convex part."""
    parts = np.array(shape.parts)
    parts.flags.writeable = False  # shared by every caller
    return parts


def _outline_rows(outline: np.ndarray, valid: np.ndarray | None, hull: HullEdges, ends: np.ndarray,
                  lengths: np.ndarray, n: int, weights: MaskFitWeights,
                  derivatives: bool) -> tuple[np.ndarray, object]:
    """The mask's outline points against the nearest part's silhouette: (B, M) residuals, and
    (`derivatives`) a function of no arguments giving their derivatives (B, M, N, 2)."""
    offsets = polygon_offsets(outline if outline.ndim == 2 else outline[:, None], hull)  # (B, P, M, E)
    per_part = largest_over_edges(offsets)  # (B, P, M)
    one_part = per_part.shape[1] == 1  # a box: its only part is the nearest
    dist = per_part[:, 0] if one_part else per_part.min(1)  # the nearest part
    value, slope = _weighted(dist, weights.outside, weights.inside, weights, False, derivatives)
    if valid is not None:  # padding of a batch's shorter outlines
        value = np.where(valid, value, 0.0)
    if not derivatives:
        return value, None

    def derivative() -> np.ndarray:
        slopes = slope if valid is None else np.where(valid, slope, 0.0)
        b, m = dist.shape
        rows, points, row = _point_rows(b, m, n)
        part = 0 if one_part else per_part.argmin(1)  # (B, M)
        # (B, M): the edge slot that gives the distance
        edge = (offsets[:, 0] if one_part else offsets[rows, part, points]).argmax(-1)
        # Each point's edge as one flat index into the hull's (B, P, E) edges: one gather a field.
        at = (rows * lengths.shape[1] + part) * lengths.shape[2] + edge
        start, direction, normal, corner = (v.reshape(-1, 2).take(at, axis=0)  # take: a quarter of indexing's cost
                                            for v in (hull.start, hull.direction, hull.normal, ends))
        d_start, d_end = _offset_gradient(outline, start, direction, normal, lengths.reshape(-1)[at][..., None] + 1e-12)
        d = np.zeros((b, m, n, 2))
        flat = d.reshape(-1, 2)  # (B M N, 2): each point's corner by one flat index
        flat[row + corner[..., 0]] = slopes[..., None] * d_start
        flat[row + corner[..., 1]] += slopes[..., None] * d_end
        return d

    return value, derivative


@lru_cache(maxsize=64)
def _point_rows(b: int, m: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B, 1) rows, (1, M) points and (B, M) each point's first corner's flat index in (B, M, N, 2)
    derivatives: fixed by the sizes, computed once for every step of a solver."""
    rows, points = np.arange(b)[:, None], np.arange(m)[None]
    row = (rows * m + points) * n
    rows.flags.writeable = points.flags.writeable = row.flags.writeable = False  # shared by every caller
    return rows, points, row


@lru_cache(maxsize=64)
def _first_corners(samples: tuple[int, ...], n: int) -> np.ndarray:
    """`samples`-shaped (B, P, E T): each edge sample's first corner's flat index in its (..., N, 2) derivatives."""
    row = np.arange(0, math.prod(samples) * n, n).reshape(samples)
    row.flags.writeable = False  # shared by every caller
    return row


@lru_cache(maxsize=None)
def _edge_samples(count: int, slots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where along an edge its `count` samples lie (count,), that for every sample of `slots` edges
    (slots count, 1), and 1 minus that: fixed, computed once."""
    t = (np.arange(count) + 0.5) / count
    share = np.tile(t, slots)[:, None]
    rest = 1 - share
    t.flags.writeable = share.flags.writeable = rest.flags.writeable = False  # shared by every caller
    return t, share, rest


def _edge_rows(hull: HullEdges, ends: np.ndarray, full: np.ndarray, sdf: Fields, n: int, weights: MaskFitWeights,
               derivatives: bool) -> tuple[np.ndarray, object]:
    """Points along the model's outline edges (`full` (B, P, E) their lengths) sampled on the mask's
    distance field: (B, P E T) residuals, and (`derivatives`) a function of no arguments giving their
    derivatives (B, P E T, N, 2)."""
    count = weights.samples_per_edge
    t, share, rest = _edge_samples(count, hull.valid.shape[-1])
    samples = hull.start[..., None, :] + hull.direction[..., None, :] * t[:, None]  # (B, P, E, T, 2)
    b, p = samples.shape[:2]
    flat = samples.reshape(b, p, -1, 2)
    keep = hull.valid.repeat(count, axis=-1)  # (B, P, E T); the method: np.repeat's answer without its wrapper
    if p == 2:  # a twobox outline inside the other part is no outline
        keep &= polygon_distance(flat, hull.swapped()) > 0
    over, gradient = bilinear_with_gradient(sdf, flat) if derivatives else (bilinear(sdf, flat), None)
    value, slope = _weighted(over, weights.overhang, weights.outside, weights, True, derivatives)
    root = np.sqrt(full / count).repeat(count, axis=-1)  # sqrt of each sample's share of the edge
    residuals = np.where(keep, value * root, 0.0).reshape(b, -1)
    if not derivatives:
        return residuals, None

    def derivative() -> np.ndarray:
        # d root / d end = (direction / L) / (2 count root); the start's is its negative.
        d_root = (hull.direction / (full[..., None] * count + 1e-12)).repeat(count, axis=-2) / (2 * root[..., None] + 1e-12)
        along = slope[..., None] * gradient * root[..., None]
        scale = keep[..., None].astype(np.float64)
        corner = ends.repeat(count, axis=-2)  # (B, P, E T, 2)
        d = np.zeros((b, p, flat.shape[2], n, 2))
        row = _first_corners(corner.shape[:-1], n)  # each sample's first corner, one flat index
        stretch = value[..., None] * d_root
        d.reshape(-1, 2)[row + corner[..., 0]] = scale * (along * rest - stretch)
        d.reshape(-1, 2)[row + corner[..., 1]] += scale * (along * share + stretch)
        return d.reshape(b, -1, n, 2)

    return residuals, derivative


@dataclass(frozen=True)
class MaskTarget:
    """What the fit reads of a mask, computed once for every shape class tried: its outline
    points and its signed distance field."""

    mask: np.ndarray  # (H, W) bool
    outline: np.ndarray  # (M, 2) px
    sdf: np.ndarray  # (H, W) px, positive outside
    cracks: tuple[np.ndarray, np.ndarray] | None = None  # every outline point of `mask` and its axis (`edge_lines.cracks`)

    @classmethod
    def of(cls, mask: np.ndarray, weights: MaskFitWeights = MaskFitWeights()) -> MaskTarget:
        every = cracks(mask)  # kept: the edge lines read them too (`edge_lines.edge_lines`)
        return cls(mask, boundary_points(mask, weights.max_boundary_points, every), signed_distance_field(mask), every)


@dataclass(frozen=True)
class StackedTargets:
    """Several masks' targets as one batch: outline points padded to the longest (K, M, 2), which
    are real (`valid` (K, M)), each one's count, and the distance fields as one `Fields`."""

    outline: np.ndarray
    valid: np.ndarray
    count: np.ndarray  # (K,)
    fields: Fields

    @classmethod
    def of(cls, targets: Sequence[MaskTarget]) -> StackedTargets:
        count = np.array([len(t.outline) for t in targets])
        outline = np.zeros((len(targets), count.max(), 2))
        valid = np.arange(count.max())[None] < count[:, None]
        outline[valid] = np.concatenate([t.outline for t in targets])
        return cls(outline, valid, count, Fields.stacked([t.sdf for t in targets]))
