"""A box's corners from its outline's straight edges (issue 37, Must haves 2 and 3): the mask's
outline split into the runs of a labelled polygon's edges (the networks' box's outline),
each run fitted by a robust line, the outline vertices where neighbouring lines cross, and the
interior corners where lines from outline vertices toward the vanishing points cross.

In a projected box every silhouette edge is a box edge, and parallel box edges meet at one
vanishing point; an interior corner's box edges to the outline vertices point at those vanishing
points, so two of them fix it (the outline fixes both interior corners of a hexagon; which of
them is in front, the Necker choice, it leaves open: the fit's labels decide). A silhouette with
a direction seen on one edge only (a face seen edge-on: a quadrilateral) fixes no vanishing point
there, and its interior corners are left to the heat maps.

Robustness: occluders only cut notches into a silhouette, so a notch's contour lies inside the
edge's line by more than the noise; Tukey's biweight gives such points no weight, and the line
is extended through the occluded stretch. Lines are fitted to the crack midpoints of the binary
mask (as `outline.boundary_points`: unbiased under the pixel-centre rule), each by its precision.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from shared.shapes import BOX_EDGES, Shape

# Tukey's scale, px: the first pass's, from the points' commonest offset along the polygon edge's
# normal (`densest_offsets`), wide enough to take the edge's tilt against the polygon's; then the
# inliers' own spread's (4.685 robust sd, Tukey's 95% efficiency), within these bounds: narrow on
# an exact mask (a notch's sides near the line weigh nothing), wide on a rough one.
FIRST_TUKEY_PX = 4.0
TUKEY_BOUNDS_PX = (1.0, 4.0)
IRLS_STEPS = 5
GATE_PX = 12.0  # outline points farther than this from every polygon edge belong to none
CORNER_MARGIN = 0.12  # the share of an edge's length at each end left out: rounded, contested corners
MIN_POINTS = 6  # an edge with fewer inliers has no line of its own
MIN_SINE = 0.05  # lines crossing at less than ~3 degrees give no vertex (it would run along them)
# Outline points per independent one (the contour noise's correlation length), in the lines' error
# bars: 8 left the truth a median 1.8 sd from noisy masks' corners (true labels, 100 dev masks a set).
CORRELATION_POINTS = 20.0
MIN_RMS_PX = 0.15  # a line's residual floor: the binary mask's own staircase
PRECISION_FLOOR_PX = 0.2  # a crack's least error across a line: the contour's own, on an exact mask
STEP = 1e-4  # the propagation's step: radians, px


@dataclass(frozen=True)
class EdgeLine:
    """One outline edge's fitted line: points p with normal . p = offset (unit normal, outward
    from the polygon), and how well the mask's outline supports it."""

    normal: np.ndarray  # (2,)
    offset: float
    inliers: int  # outline points with weight
    rms_px: float  # the inliers' rms distance from the line
    centre: np.ndarray  # (2,) the inliers' weighted centre
    length_sd: float  # px, the inliers' standard deviation along the line

    def homogeneous(self) -> np.ndarray:
        """(a, b, c) with a x + b y + c = 0, (a, b) of unit length."""
        return np.array([self.normal[0], self.normal[1], -self.offset])


@dataclass(frozen=True)
class OutlineEdges:
    """A labelled polygon's edges fitted to a mask: `labels` (V,) the keypoint index of each
    polygon vertex in order, `lines` (V,) the line of the edge from vertex i to i + 1 (None: too
    few outline points)."""

    labels: np.ndarray
    lines: tuple[EdgeLine | None, ...]


@dataclass(frozen=True)
class EdgeCorners:
    """A box's corners as its outline fixes them: `keypoints` (N, 2) with NaN where it does not,
    `from_outline` (N,) which are fixed, `on_outline` (N,) which are outline vertices, and the Necker
    alternative: the interior corners' positions with front and back exchanged (N, 2), NaN outside
    the interior ones, or None where the outline fixes no interior corner."""

    keypoints: np.ndarray
    from_outline: np.ndarray
    on_outline: np.ndarray
    sd_px: np.ndarray  # (N,) each fixed corner's standard deviation from its lines' (inf where not fixed)
    necker: np.ndarray | None

    @property
    def interior_fixed(self) -> bool:
        """Every interior corner fixed by the outline."""
        return bool(self.from_outline[~self.on_outline].all()) and (~self.on_outline).any()


def cracks(mask: np.ndarray, window: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) the mask's outline points, the midpoints between 4-neighbouring pixel centres of which
    one is in and one out (all of them: `outline.boundary_points` takes some), and (M,) the axis each crack
    crosses: 0 between a row's neighbours (its point is uncertain along x), 1 between a column's.
    `window` (left, top, right, bottom), pixel bounds: only the cracks between pixels inside it."""
    left, top, right, bottom = window if window is not None else (0, 0, mask.shape[1], mask.shape[0])
    m = mask[top:bottom, left:right].astype(bool)
    ys, xs = np.nonzero(m[:, :-1] != m[:, 1:])
    across_x = np.stack([xs + 0.5 + left, ys + top], axis=1)
    ys, xs = np.nonzero(m[:-1] != m[1:])
    across_y = np.stack([xs + left, ys + 0.5 + top], axis=1)
    axis = np.concatenate([np.zeros(len(across_x), dtype=np.intp), np.ones(len(across_y), dtype=np.intp)])
    return np.concatenate([across_x, across_y]).astype(np.float64), axis


def windowed(points: np.ndarray, axis: np.ndarray, window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Of a mask's `cracks` (points (M, 2), axis (M,)), those `cracks(mask, window)` finds: both pixels inside
    the window, in the same order."""
    left, top, right, bottom = window
    x, y = points[:, 0], points[:, 1]
    across_x = axis == 0  # between a row's neighbours: x is a half
    inside = np.where(across_x, (x > left) & (x < right - 1) & (y >= top) & (y < bottom),
                      (x >= left) & (x < right) & (y > top) & (y < bottom - 1))
    return points[inside], axis[inside]


def outline_polygon(keypoints: np.ndarray) -> np.ndarray:
    """(V,) the keypoint indices of the convex hull's vertices of (N, 2) corners, counter-clockwise
    in the image (y down: clockwise on screen)."""
    hull = cv2.convexHull(keypoints.astype(np.float32), returnPoints=False).ravel()
    return hull if signed_area(keypoints[hull]) > 0 else hull[::-1]


def signed_area(polygon: np.ndarray) -> float:
    """The shoelace area of a polygon (V, 2): its sign is its orientation."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def edge_lines(mask: np.ndarray, keypoints: np.ndarray, labels: np.ndarray,
               every: tuple[np.ndarray, np.ndarray] | None = None) -> OutlineEdges:
    """The lines of the polygon `keypoints[labels]`'s edges (a convex outline, `outline_polygon`'s
    order) fitted to the (H, W) mask's outline points (`cracks`), each point given to the nearest
    edge within GATE_PX, away from its ends (`fit_lines`). `every`: the mask's `cracks`, where the
    caller has them (`outline.MaskTarget`): those of the polygon's window picked, not found again."""
    polygon = keypoints[labels]
    low = np.floor(polygon.min(0) - GATE_PX - 2).astype(int)
    high = np.ceil(polygon.max(0) + GATE_PX + 2).astype(int)
    window = (max(low[0], 0), max(low[1], 0), min(high[0], mask.shape[1]), min(high[1], mask.shape[0]))
    if not (window[0] < window[2] and window[1] < window[3]):
        points, axis = cracks(mask) if every is None else every
    else:
        points, axis = cracks(mask, window) if every is None else windowed(*every, window)
    start, direction = polygon, np.roll(polygon, -1, axis=0) - polygon
    length = np.linalg.norm(direction, axis=1) + 1e-12
    tangent = direction / length[:, None]
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # outward for counter-clockwise (y down)
    relative = points[:, None] - start[None]  # (M, V, 2)
    along = np.einsum("mvk,vk->mv", relative, tangent) / length  # share of the edge, 0 at its start
    across = np.einsum("mvk,vk->mv", relative, normal)
    inside = (along > CORNER_MARGIN) & (along < 1 - CORNER_MARGIN)
    distance = np.where(inside, np.abs(across), np.inf)
    nearest = np.argmin(distance, axis=1)
    kept = distance[np.arange(len(points)), nearest] < GATE_PX
    return OutlineEdges(labels, fit_lines(points[kept], axis[kept], nearest[kept], normal))


def fit_lines(points: np.ndarray, axis: np.ndarray, edge: np.ndarray, normal: np.ndarray) -> tuple[EdgeLine | None, ...]:
    """The line of each of V edges through its (M, 2) crack points (`cracks`: `axis` (M,) the one each
    is uncertain along; `edge` (M,) whose it is), by iteratively reweighted total least squares with
    Tukey's biweight (its scale: FIRST_TUKEY_PX, then the inliers' spread's), from the line of normal
    `normal` (V, 2) through the points' densest offset along it (`densest_offsets`); None where fewer
    than MIN_POINTS keep a weight. All edges at once: a few numpy calls an iteration, whatever V.

    Each point is weighed by its precision across the line too: a crack's midpoint lies within half
    a pixel of the outline along its axis, so across a line of normal n its error is n[axis] / sqrt(12).
    On a line near a row or column, the few cracks across it (the staircase's steps) fix it to
    sub-pixel precision, and the many along it only to the half-integer they all share (20 random
    boxes' exact masks: the worst vertex 1.19 px unweighted, 0.69 px weighted)."""
    v = len(normal)
    normal = normal.copy()
    offset = densest_offsets((points * normal[edge]).sum(1), edge, v)
    scale = np.full(v, FIRST_TUKEY_PX)
    alive = np.bincount(edge, minlength=v) >= MIN_POINTS
    robust = None
    for _ in range(IRLS_STEPS):
        residual = (points * normal[edge]).sum(1) - offset[edge]
        if robust is not None:  # 1.4826 median |r|: the normal sd the inliers' spread says
            spread = _medians(np.abs(residual), robust > 0, edge, v)
            scale = np.where(np.isfinite(spread), np.clip(4.685 * 1.4826 * spread, *TUKEY_BOUNDS_PX), FIRST_TUKEY_PX)
        s = scale[edge]
        robust = np.where(np.abs(residual) < s, (1 - (residual / s) ** 2) ** 2, 0.0)
        alive &= np.bincount(edge, robust > 0, minlength=v) >= MIN_POINTS
        # the first pass unweighed: a notch's sides cross a line's normal, as its steps do
        precision = 1 / (normal[edge, axis] ** 2 / 12 + PRECISION_FLOOR_PX**2)
        weights = robust * np.where(s == FIRST_TUKEY_PX, 1.0, precision)
        total = np.maximum(np.bincount(edge, weights, minlength=v), 1e-300)
        centre = np.stack([np.bincount(edge, weights * points[:, k], minlength=v) / total for k in (0, 1)], axis=1)
        d = points - centre[edge]
        xx, xy, yy = (np.bincount(edge, weights * a * b, minlength=v) for a, b in ((d[:, 0], d[:, 0]),
                                                                             (d[:, 0], d[:, 1]), (d[:, 1], d[:, 1])))
        major = 0.5 * np.arctan2(2 * xy, xx - yy)  # the most-spread direction; the normal is across it
        fitted = np.stack([-np.sin(major), np.cos(major)], axis=1)
        normal = np.where(((fitted * normal).sum(1) >= 0)[:, None], fitted, -fitted)  # keep it outward
        offset = (normal * centre).sum(1)
    residual = (points * normal[edge]).sum(1) - offset[edge]
    inlier = weights > 0
    count = np.bincount(edge, inlier, minlength=v)
    along = (d * np.stack([-normal[:, 1], normal[:, 0]], axis=1)[edge]).sum(1)
    mean_along = np.bincount(edge, inlier * along, minlength=v) / np.maximum(count, 1)
    length_sd = np.sqrt(np.maximum(np.bincount(edge, inlier * along**2, minlength=v) / np.maximum(count, 1)
                                   - mean_along**2, 0))
    rms = np.sqrt(np.bincount(edge, inlier * residual**2, minlength=v) / np.maximum(count, 1))
    return tuple(EdgeLine(normal[k], float(offset[k]), int(count[k]), float(rms[k]), centre[k], float(length_sd[k]))
                 if alive[k] else None for k in range(v))


def _medians(values: np.ndarray, chosen: np.ndarray, edge: np.ndarray, v: int) -> np.ndarray:
    """(V,) each edge's median of its chosen (M,) values (NaN for none), as np.median takes it."""
    values, edge = values[chosen], edge[chosen]
    order = np.lexsort((values, edge))
    ordered = values[order]
    count = np.bincount(edge, minlength=v)
    first = np.cumsum(count) - count
    low, high = first + (count - 1) // 2, first + count // 2
    safe = np.minimum(np.stack([low, high]), max(len(ordered) - 1, 0))
    return np.where(count > 0, ordered[safe].mean(0) if len(ordered) else np.nan, np.nan)


def densest_offsets(offsets: np.ndarray, edge: np.ndarray, v: int) -> np.ndarray:
    """(V,): where each edge's offsets along its normal crowd most, in a 3 px window, the outermost
    such window on a tie: the edge's own points. Not their median: an occluder's notch adds its sides
    and its floor to the points near an edge, and a notch 10 px deep over a third of an edge gave it
    more points than the edge kept (the median inside the building, the line on the notch's floor)."""
    low = np.full(v, np.inf)
    np.minimum.at(low, edge, offsets)
    low = np.floor(np.where(np.isfinite(low), low, 0.0))
    bins = (offsets - low[edge]).astype(np.intp)
    width = int(bins.max()) + 3 if len(bins) else 3
    counts = np.bincount(edge * width + bins, minlength=v * width).reshape(v, width)
    padded = np.zeros((v, width + 2), dtype=counts.dtype)  # np.pad's zeros either side, without its wrapper (0.1 ms)
    padded[:, 1:-1] = counts
    window = padded[:, :-2] + padded[:, 1:-1] + padded[:, 2:]
    last = np.zeros(v, dtype=np.intp)
    np.maximum.at(last, edge, bins)
    window[np.arange(width)[None] > last[:, None]] = -1  # past an edge's own last bin
    best = width - 1 - np.argmax(window[:, ::-1], axis=1)  # the outermost of the largest
    return low + best + 0.5


def corners_from_edges(edges: OutlineEdges, shape: Shape) -> EdgeCorners:
    """A box's corners as the fitted edges fix them, labelled as the polygon's vertices are: the
    outline vertices where lines cross, each interior corner where the lines from its outline
    neighbours toward their edges' vanishing points cross, each with its standard deviation from
    the lines' (`corner_spread`), and the Necker alternative (`necker_alternative`)."""
    layout = box_outline(shape, tuple(int(k) for k in edges.labels))
    lines = np.array([np.full(3, np.nan) if line is None else line.homogeneous() for line in edges.lines])
    keypoints = layout.corners(lines[None])[0]
    sd = corner_spread(edges, layout, keypoints)
    fixed = np.isfinite(keypoints).all(1) & np.isfinite(sd)
    on_outline = np.zeros(shape.num_keypoints, dtype=bool)
    on_outline[edges.labels] = True
    necker = necker_alternative(keypoints, on_outline, box_directions(shape)) if layout.interior_known else None
    return EdgeCorners(np.where(fixed[:, None], keypoints, np.nan), fixed, on_outline, np.where(fixed, sd, np.inf),
                          necker)


@lru_cache(maxsize=256)
def box_outline(shape: Shape, labels: tuple[int, ...]) -> BoxOutline:
    """`BoxOutline.of`, kept: a few dozen labellings recur."""
    return BoxOutline.of(shape, np.array(labels))


@dataclass(frozen=True)
class BoxOutline:
    """How a box's corners follow from its outline's V edge lines, for one labelling of the polygon:
    which lines meet at each vanishing point (two a direction: a hexagon), and for each interior
    corner, its outline neighbours (vertex indices) and the direction toward each."""

    labels: np.ndarray  # (V,) keypoint index of each polygon vertex
    num_keypoints: int
    pairs: np.ndarray | None  # (3, 2) the edge indices of each direction's two lines; None: no vanishing points
    interior: tuple[tuple[int, tuple[int, ...], tuple[int, ...]], ...]  # (corner, vertices, directions)

    @classmethod
    def of(cls, shape: Shape, labels: np.ndarray) -> BoxOutline:
        directions = box_directions(shape)
        v = len(labels)
        edge_direction = [directions.get((int(labels[i]), int(labels[(i + 1) % v]))) for i in range(v)]
        by_direction = [[i for i, d in enumerate(edge_direction) if d == k] for k in range(3)]
        if None in edge_direction or any(len(edges) != 2 for edges in by_direction):
            return cls(labels, shape.num_keypoints, None, ())
        where = {int(label): i for i, label in enumerate(labels)}
        interior = []
        for corner in sorted(set(range(shape.num_keypoints)) - set(where)):
            neighbours = [(where[b], d) for (a, b), d in directions.items() if a == corner and b in where]
            interior.append((corner, tuple(n for n, _ in neighbours), tuple(d for _, d in neighbours)))
        return cls(labels, shape.num_keypoints, np.array(by_direction), tuple(interior))

    @property
    def interior_known(self) -> bool:
        return self.pairs is not None

    def corners(self, lines: np.ndarray) -> np.ndarray:
        """(B, N, 2) corners (NaN where not fixed) from (B, V, 3) homogeneous lines with unit normals
        (NaN rows: no line): a batch, so that perturbed lines cost one pass (`corner_spread`)."""
        b = len(lines)
        out = np.full((b, self.num_keypoints, 2), np.nan)
        before = np.roll(lines, 1, axis=1)
        vertices = cross(before, lines)  # (B, V, 3): vertex i between edges i - 1 and i
        sine = np.abs(before[..., 0] * lines[..., 1] - before[..., 1] * lines[..., 0])
        with np.errstate(divide="ignore", invalid="ignore"):  # parallel lines: no vertex, NaN below
            points = vertices[..., :2] / vertices[..., 2:]
        points[sine < MIN_SINE] = np.nan
        out[:, self.labels] = points
        if self.pairs is None:
            return out
        vanishing = cross(lines[:, self.pairs[:, 0]], lines[:, self.pairs[:, 1]])  # (B, 3, 3)
        for corner, neighbours, directions in self.interior:
            if len(neighbours) < 2:
                continue
            through = np.concatenate([points[:, neighbours], np.ones((b, len(neighbours), 1))], axis=2)
            toward = cross(through, vanishing[:, directions])  # (B, J, 3)
            toward /= np.sqrt(toward[..., :1] ** 2 + toward[..., 1:2] ** 2) + 1e-300
            out[:, corner] = crossings(toward)
        return out


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3) cross products of homogeneous lines or points: np.cross's checks cost more than it."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def crossings(lines: np.ndarray) -> np.ndarray:
    """(B, 2): for each of B sets of J >= 2 homogeneous lines with unit normals (B, J, 3), the point
    nearest all of them (least squares); NaN where they are (nearly) parallel: the normals' Gram
    matrix's eigenvalues further apart than MIN_SINE squared."""
    normals, offsets = lines[..., :2], -lines[..., 2]
    gram = np.swapaxes(normals, 1, 2) @ normals  # (B, 2, 2)
    right = np.einsum("bjk,bj->bk", normals, offsets)
    trace, det = gram[:, 0, 0] + gram[:, 1, 1], gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    root = np.sqrt(np.maximum(trace**2 / 4 - det, 0))
    conditioned = (trace / 2 - root) >= MIN_SINE**2 * (trace / 2 + root)
    det = np.where(conditioned, det, 1.0)  # the 2 x 2 inverse by hand: np.linalg.solve costs more a call
    solved = np.stack([gram[:, 1, 1] * right[:, 0] - gram[:, 0, 1] * right[:, 1],
                       gram[:, 0, 0] * right[:, 1] - gram[:, 0, 1] * right[:, 0]], axis=1) / det[:, None]
    return np.where(conditioned[:, None], solved, np.nan)


def corner_spread(edges: OutlineEdges, layout: BoxOutline, keypoints: np.ndarray) -> np.ndarray:
    """(N,) each corner's standard deviation (px, the rms of its two axes') from its lines', by
    first-order propagation: each line shifted along its normal and turned about its inliers'
    centre by a small step, all at once. A line's offset sd is its inliers' rms over the square
    root of their independent count (contour noise is correlated along CORRELATION_POINTS), its
    angle's that over their spread along it. NaN where a corner is not fixed."""
    base = np.array([np.full(3, np.nan) if line is None else line.homogeneous() for line in edges.lines])
    steps, sds = [], []
    for i, line in enumerate(edges.lines):
        if line is None:
            continue
        independent = max(line.inliers / CORRELATION_POINTS, 2.0)
        rms = max(line.rms_px, MIN_RMS_PX)
        shifted = base.copy()
        shifted[i, 2] -= STEP
        turned = base.copy()
        angle = np.arctan2(line.normal[1], line.normal[0]) + STEP
        normal = np.array([np.cos(angle), np.sin(angle)])
        turned[i] = [normal[0], normal[1], -normal @ line.centre]
        steps += [shifted, turned]
        sds += [rms / np.sqrt(independent), rms / (np.sqrt(independent) * max(line.length_sd, 1.0))]
    if not steps:
        return np.full(len(keypoints), np.nan)
    moved = layout.corners(np.array(steps))  # (S, N, 2)
    jacobian = (moved - keypoints[None]) / STEP * np.array(sds)[:, None, None]
    return np.sqrt(np.sum(jacobian**2, axis=(0, 2)) / 2)


@lru_cache(maxsize=None)
def box_directions(shape: Shape) -> dict[tuple[int, int], int]:
    """Each box edge (keypoint pair, both orders) of a one-part shape -> its direction: 0 height,
    1 width, 2 depth (the Table 1 bit the two corners differ in: bottom, left, front)."""
    part = shape.parts[0]
    directions = {}
    for a, b in BOX_EDGES:
        direction = {1: 0, 2: 1, 4: 2}[a ^ b]
        directions[part[a], part[b]] = directions[part[b], part[a]] = direction
    return directions


def necker_alternative(fixed: np.ndarray, on_outline: np.ndarray,
                       directions: dict[tuple[int, int], int]) -> np.ndarray | None:
    """The interior corners (N, 2; NaN elsewhere) of the box seen the other way round (Necker's
    cube): the same outline, each interior point taken by the interior corner opposite it through
    the box (the front one by the back one). A hexagon's two interior points are one corner and its
    diagonal opposite: exchanged, the other box. None when the interior is not two fixed corners
    opposite through the box."""
    interior = np.flatnonzero(~on_outline)
    if len(interior) != 2 or not np.isfinite(fixed[interior]).all():
        return None
    a, b = interior
    if (a, b) in directions:
        return None  # neighbours through one edge, not opposite through the box: no such alternative
    alternative = np.full_like(fixed, np.nan)
    alternative[a], alternative[b] = fixed[b], fixed[a]
    return alternative
