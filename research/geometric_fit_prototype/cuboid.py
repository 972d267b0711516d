"""Perspective cuboid (box / twobox) geometry: camera model, projection, lift from corners,
fit to a binary mask, and shape selection.

Why a parametric model: the networks return 8/14 free points that are not the projection of
any box. Fitting a camera + cuboid makes every output a real projection (ratios come from the
3D extents, hidden corners follow from the visible outline), and lets the fit be judged by the
mask at the input's own resolution.

Parameter vector (one row per hypothesis, batched everywhere, float64):

    0 log width   1 log depth          (height of the (R)/only part is 1: the scale gauge)
    2..4 rotation vector (object -> camera, OpenCV camera: x right, y down, z forward)
    5, 6 tx, ty   object-centre offset in height units, divided by the centre's depth
    7 log s       px per height unit at the centre's depth (= f / tz)
    8 k           1 / tz, perspective strength (0 = weak perspective: smooth through it)
    9, 10 cx, cy  principal point, px
    twobox only: 11 split (share of the width taken by the (R) part), 12 log hL (left height)

    u = c + s * (R X + t)_xy / (1 + k (R X)_z)   with t = (tx, ty) in height units

This is the pinhole camera x = f X / Z + c with tz = 1/k and f = s/k, rewritten so that weak
perspective (k -> 0) is an ordinary point, not infinity: LM then walks through near-affine
views without the f/distance blow-up. A discrete `mirror` flag reflects the object in x before
the rotation: viewer naming (LEFT = image-left, FRONT = nearer) can make the labelled corners
a reflected box, which no rotation reaches.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shared.shapes import Shape

# --- camera model -----------------------------------------------------------------------

_SIDES = np.array([[(c >> 1) & 1, c & 1, (c >> 2) & 1] for c in range(8)], dtype=np.float64)  # left, bottom, front


def _box(x_right, x_left, y_top, y_bottom, depth) -> np.ndarray:
    """(B, 8, 3) corners of axis-aligned boxes in Table 1 order; arguments are (B,) arrays."""
    left, bottom, front = _SIDES[:, 0], _SIDES[:, 1], _SIDES[:, 2]
    x = np.where(left, x_left[:, None], x_right[:, None])
    y = np.where(bottom, y_bottom[:, None], y_top[:, None])
    z = np.where(front, -depth[:, None] / 2, depth[:, None] / 2)
    return np.stack([x, y, z], axis=-1)


def object_points(params: np.ndarray, shape: Shape, mirror: np.ndarray) -> np.ndarray:
    """(B, N, 3) labelled object corners for (B, P) params; `mirror` (B,) bool reflects x."""
    w, d = np.exp(params[:, 0]), np.exp(params[:, 1])
    half = np.full_like(w, 0.5)
    if len(shape.parts) == 1:
        points = _box(w / 2, -w / 2, -half, half, d)
    else:
        middle = w / 2 - params[:, 11] * w
        points = np.empty((len(params), 14, 3))
        points[:, list(shape.parts[0])] = _box(w / 2, middle, -half, half, d)
        points[:, list(shape.parts[1])] = _box(middle, -w / 2, half - np.exp(params[:, 12]), half, d)
    points[..., 0] *= np.where(mirror, -1.0, 1.0)[:, None]
    return points


def rotation_matrices(rotvec: np.ndarray) -> np.ndarray:
    """(B, 3) rotation vectors -> (B, 3, 3) matrices (Rodrigues, stable near 0)."""
    theta = np.linalg.norm(rotvec, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(theta)) / safe**2)
    x, y, z = rotvec.T
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=1).reshape(-1, 3, 3)
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def rotation_vector(matrix: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(matrix, dtype=np.float64))[0].ravel()


def camera_points(params: np.ndarray, shape: Shape, mirror: np.ndarray) -> np.ndarray:
    """(B, N, 3) corners rotated into the camera, object centre at the origin (not translated)."""
    return object_points(params, shape, mirror) @ rotation_matrices(params[:, 2:5]).transpose(0, 2, 1)


def project(params: np.ndarray, shape: Shape, mirror) -> np.ndarray:
    """(B, P) or (P,) params -> (B, N, 2) or (N, 2) image points, in the model's corner labels."""
    single = params.ndim == 1
    params = np.atleast_2d(params)
    mirror = np.broadcast_to(np.asarray(mirror, dtype=bool), (len(params),))
    rotated = camera_points(params, shape, mirror)
    depth = 1.0 + params[:, 8, None] * rotated[..., 2]
    xy = (rotated[..., :2] + params[:, None, 5:7]) * (np.exp(params[:, 7])[:, None, None] / depth[..., None])
    image = xy + params[:, None, 9:11]
    return image[0] if single else image


def depths(params: np.ndarray, shape: Shape, mirror) -> np.ndarray:
    """(B, N) relative depths of the corners (z / tz): what FRONT/BACK naming compares."""
    params = np.atleast_2d(params)
    mirror = np.broadcast_to(np.asarray(mirror, dtype=bool), (len(params),))
    return 1.0 + params[:, 8, None] * camera_points(params, shape, mirror)[..., 2]


def ratios(params: np.ndarray, shape: Shape) -> np.ndarray:
    """(B, 2 or 4) depth/height, width/height in `shape.ratio_names` order."""
    params = np.atleast_2d(params)
    w, d = np.exp(params[:, 0]), np.exp(params[:, 1])
    if len(shape.parts) == 1:
        return np.stack([d, w], axis=1)
    split, h_left = params[:, 11], np.exp(params[:, 12])
    return np.stack([d, split * w, d / h_left, (1 - split) * w / h_left], axis=1)


def viewer_order(shape: Shape, image: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The generator's naming rule (cuboidgen.scene.viewer_order) applied to a fitted model's
    projection: the index order that makes LEFT image-left and FRONT nearer."""
    order = np.arange(shape.num_keypoints)
    left, right = shape.having("LEFT"), shape.having("RIGHT")
    if image[left, 0].sum() > image[right, 0].sum():
        order = order[shape.mirror_left_right]
    if depth[order[shape.having("FRONT")]].sum() > depth[order[shape.having("BACK")]].sum():
        order = order[shape.mirror_front_back]
    return order


@dataclass(frozen=True)
class Camera:
    """One fitted (or generated) cuboid and camera: params as above and the reflection flag."""

    shape: Shape
    params: np.ndarray  # (P,)
    mirror: bool

    def keypoints(self) -> np.ndarray:
        return project(self.params, self.shape, self.mirror)

    def named_keypoints(self) -> np.ndarray:
        """Keypoints renamed by the viewer rules (a fit may have drifted past a side)."""
        image = self.keypoints()
        order = viewer_order(self.shape, image, depths(self.params, self.shape, self.mirror)[0])
        return image[order]

    def ratios(self) -> np.ndarray:
        return ratios(self.params, self.shape)[0]

    @property
    def focal(self) -> float:
        return float(np.exp(self.params[7]) / self.params[8]) if self.params[8] > 0 else np.inf


# --- the generator's parameters in this model ---------------------------------------------

def from_generator(shape: Shape, gen: dict) -> Camera:
    """The Camera whose projection, in Table 1/2 labels, equals the generator's View.keypoints.

    The generator poses its object with L (rotation, camera tilt folded in, mirrored by `flip`)
    and names corners after projection (swap_left_right / swap_front_back). The named corners
    are the object's corners reflected by G = diag(+-1, 1, +-1); M = L G is then a rotation or a
    reflection, and a reflection becomes a rotation of the x-mirrored object.
    """
    from cuboidgen.scene import camera_tilt, rotation

    ct, st = camera_tilt(gen["camera_pitch_deg"])
    r1, r2, r3 = (np.array(r) for r in rotation(gen["pitch_deg"], gen["yaw_deg"], gen["roll_deg"]))
    linear = np.array([r1, ct * r2 + st * r3, ct * r3 - st * r2])
    y, z = gen["offset_y"], gen["distance"]
    offset = np.array([gen["offset_x"], ct * y + st * z, ct * z - st * y])
    if gen["flip"]:
        linear[0], offset[0] = -linear[0], -offset[0]
    sx, sz = (-1.0 if gen["swap_left_right"] else 1.0), (-1.0 if gen["swap_front_back"] else 1.0)
    m = linear @ np.diag([sx, 1.0, sz])
    mirror = np.linalg.det(m) < 0
    rot = m @ np.diag([-1.0, 1.0, 1.0]) if mirror else m
    w, h, d = gen["width"], gen["height"], gen["depth"]
    if len(shape.parts) == 1:
        scale, shift, extra = h, np.zeros(3), []
    else:
        low = h * gen["height_ratio"]
        h_left, h_right = (h, low) if gen["left_taller"] else (low, h)
        split = gen["split"]
        if gen["swap_left_right"]:
            split, h_left, h_right = 1 - split, h_right, h_left
        scale, shift = h_right, np.array([0.0, h / 2 - h_right / 2, 0.0])  # bottoms: h/2 there, 1/2 here
        extra = [split, np.log(h_left / h_right)]
    t = (offset + m @ shift) / scale  # camera = scale * (rot X_model + t)
    s = gen["frame_scale"] / t[2]
    params = np.array([np.log(w / scale), np.log(d / scale), *rotation_vector(rot), t[0], t[1], np.log(s),
                       1.0 / t[2], *gen["frame_origin"], *extra])
    return Camera(shape, params, bool(mirror))


# --- batched Levenberg-Marquardt ------------------------------------------------------------

@dataclass(frozen=True)
class Solved:
    """LM result per hypothesis: params (B, P) and final cost (B,) = 0.5 * sum of squares."""

    params: np.ndarray
    cost: np.ndarray


def levenberg_marquardt(residual, x0: np.ndarray, iterations: int = 50, step: float = 1e-7,
                        tolerance: float = 1e-12) -> Solved:
    """Minimise 0.5 |residual(x, rows)|^2 for every row of x0 at once.

    `residual(x, rows)` maps (B', P) params and (B',) hypothesis indices to (B', M) residuals,
    so one call evaluates all hypotheses and all forward-difference columns of the Jacobian
    (B * (P + 1) rows): numpy's per-call cost is paid once per iteration, not per start.
    """
    x = x0.copy()
    b, p = x.shape
    rows = np.arange(b)
    fd_rows = np.repeat(rows, p + 1)
    damping = np.full(b, 1e-3)
    r = residual(x, rows)
    cost = 0.5 * (r**2).sum(1)
    active = np.ones(b, dtype=bool)
    eye = np.eye(p)
    for _ in range(iterations):
        probe = np.repeat(x[:, None, :], p + 1, axis=1)
        probe[:, 1:] += eye * step
        values = residual(probe.reshape(-1, p), fd_rows).reshape(b, p + 1, -1)
        r = values[:, 0]
        jac = (values[:, 1:] - r[:, None]).transpose(0, 2, 1) / step  # (B, M, P)
        jtj = jac.transpose(0, 2, 1) @ jac
        grad = np.einsum("bmp,bm->bp", jac, r)
        diag = np.einsum("bii->bi", jtj)
        system = jtj + (damping[:, None] * (diag + 1e-9))[:, :, None] * eye
        delta = -np.linalg.solve(system, grad[..., None])[..., 0]
        trial = x + delta * active[:, None]
        new_cost = np.nan_to_num(0.5 * (residual(trial, rows) ** 2).sum(1), nan=np.inf)
        better = (new_cost < cost) & active
        x[better] = trial[better]
        gain = np.where(better, cost - new_cost, 0.0)
        cost = np.where(better, new_cost, cost)
        damping = np.where(better, damping / 3, damping * 4)
        active &= ~((better & (gain <= tolerance * (cost + 1e-12))) | (damping > 1e10) | (cost < 1e-20))
        if not active.any():
            break
    return Solved(x, cost)


# --- lift: named corners -> camera -----------------------------------------------------------

def _edge_means(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean 2D edge vectors of one labelled box (8, 2): toward RIGHT, BOTTOM and BACK."""
    left, bottom, front = (_SIDES[:, k].astype(bool) for k in range(3))
    right_minus_left = points[~left].mean(0) - points[left].mean(0)
    down = points[bottom].mean(0) - points[~bottom].mean(0)
    back = points[~front].mean(0) - points[front].mean(0)
    return right_minus_left, down, back


def affine_box(points: np.ndarray) -> tuple[float, float, float, np.ndarray]:
    """Weak-perspective lift of one labelled box (8, 2): width, depth (height 1), scale s and the
    camera rotation's first two rows.

    In an affine view the image edge vectors are s R [w, 1, d] per axis; R's first two rows are
    orthonormal, which gives two linear equations in 1/w^2 and 1/d^2.
    """
    ux, uy, uz = _edge_means(points)
    a = np.array([[ux[0] * ux[1], uz[0] * uz[1]], [ux[0] ** 2 - ux[1] ** 2, uz[0] ** 2 - uz[1] ** 2]])
    rhs = -np.array([uy[0] * uy[1], uy[0] ** 2 - uy[1] ** 2])
    try:
        inv_w2, inv_d2 = np.linalg.solve(a, rhs)
    except np.linalg.LinAlgError:
        inv_w2 = inv_d2 = -1.0
    s = np.linalg.norm(uy)
    # Perspective or noise can make the system inconsistent: fall back to image lengths.
    w = 1 / np.sqrt(inv_w2) if inv_w2 > 0 else max(np.linalg.norm(ux) / s, 0.05)
    d = 1 / np.sqrt(inv_d2) if inv_d2 > 0 else max(np.linalg.norm(uz) / s, 0.05)
    rows = np.stack([ux / w, uy, uz / d], axis=1)  # (2, 3) = s * R[:2]
    s = np.sqrt(0.5 * (rows**2).sum())
    return w, d, s, rows / s


def _rotation_from_rows(rows: np.ndarray) -> np.ndarray:
    """The nearest rotation whose first two rows are `rows` (2, 3)."""
    m = np.vstack([rows, np.cross(rows[0], rows[1])])
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt


def affine_starts(points: np.ndarray, shape: Shape, k_starts=(0.0,)) -> tuple[np.ndarray, np.ndarray]:
    """Start params (H, P) and mirror flags (H,) from labelled image corners (N, 2):
    the two depth orders of the affine lift (Necker: R's third row +-, the - one being a
    rotation of the x-mirrored box) times each start of the perspective strength k (units 1/height)."""
    parts = [points[list(p)] for p in shape.parts]
    w, d, s, rows = affine_box(parts[0])
    extra = []
    if len(shape.parts) == 2:
        w_left, _, s_left, _ = affine_box(parts[1])
        h_left = s_left / s  # each part's affine lift sets its own height to 1
        width = w + w_left * h_left
        extra, w = [w / width, np.log(h_left)], width
    centre = points.mean(0)
    starts, mirrors = [], []
    for mirror in (False, True):
        r = _rotation_from_rows(rows)
        if mirror:  # same first two rows for the reflected object: R F with R's third row negated
            r = np.vstack([r[:2], -r[2]]) @ np.diag([-1.0, 1.0, 1.0])
        for k in k_starts:
            starts.append([np.log(w), np.log(d), *rotation_vector(r), 0.0, 0.0, np.log(s), k,
                           centre[0], centre[1], *extra])
            mirrors.append(mirror)
    params, mirror = np.array(starts), np.array(mirrors)
    # The object centre is not the corners' centroid (twobox, perspective): shift c to match.
    params[:, 9:11] += centre - project(params, shape, mirror).mean(1)
    return params, mirror


@dataclass(frozen=True)
class Lifted:
    """The best camera for given corners, and every hypothesis tried (for ambiguity checks)."""

    camera: Camera
    rms: float  # px
    hypotheses: np.ndarray  # (H, P)
    mirrors: np.ndarray  # (H,)
    costs: np.ndarray  # (H,)


def lift(points: np.ndarray, shape: Shape, weights: np.ndarray | None = None,
         k_starts=((0.0, 0.15, 0.3, 0.5), (0.75, 1.0, 1.5)), iterations: int = 300, tolerance: float = 0.0,
         accept_rms: float = 1e-6) -> Lifted:
    """Named image corners (N, 2) -> the camera + cuboid that projects onto them (weighted
    least squares; `weights` (N,) per corner, e.g. network confidences).

    `k_starts` are groups of perspective-strength starts, tried in turn until one reaches
    `accept_rms` px: strongly perspective views (paper: distance down to 1.2 heights) need a
    large-k start, most views are solved by the first group."""
    weights = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    groups = k_starts if isinstance(k_starts[0], (tuple, list)) else (k_starts,)
    sqrt_w = np.sqrt(weights)[None, :, None]
    params, mirrors, costs = [], [], []
    for group in groups:
        starts, flags = affine_starts(points, shape, group)

        def residual(x, rows, flags=flags):
            return ((project(x, shape, flags[rows]) - points) * sqrt_w).reshape(len(x), -1)

        solved = levenberg_marquardt(residual, starts, iterations, tolerance=tolerance)
        params.append(solved.params); mirrors.append(flags); costs.append(solved.cost)
        if np.sqrt(2 * solved.cost.min() / len(points)) < accept_rms:
            break
    params, mirrors, costs = np.concatenate(params), np.concatenate(mirrors), np.concatenate(costs)
    best = int(np.argmin(costs))
    rms = float(np.sqrt(2 * costs[best] / len(points)))
    return Lifted(Camera(shape, params[best], bool(mirrors[best])), rms, params, mirrors, costs)


# --- fit to a mask -------------------------------------------------------------------------

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


@dataclass(frozen=True)
class MaskFit:
    """A cuboid fitted to a mask: the camera, its named keypoints, and how well it explains the mask."""

    camera: Camera
    keypoints: np.ndarray  # (N, 2) viewer-named, input px
    cost: float  # the LM objective at the optimum
    iou: float  # IoU of the model's silhouette (raster.py rule) with the input mask
    missed: float  # share of mask pixels outside the model


def fit_mask(mask: np.ndarray, shape: Shape, corners: np.ndarray, confidence: np.ndarray,
             prior_ratios: np.ndarray | None = None, weights: MaskFitWeights = MaskFitWeights(),
             starts: int = 2, iterations: int = 20) -> MaskFit:
    """Cuboid params that explain a binary mask (input resolution), started from the lift of the
    network corners (the `starts` best lift hypotheses) and pulled toward them by confidence.
    `prior_ratios` (the network's ratio head, `shape.ratio_names` order) anchors the extents the
    outline leaves free: near-frontal views trade depth against yaw and focal length (RESULTS.md)."""
    lifted = lift(corners, shape, confidence, k_starts=(0.0, 0.3), iterations=15, tolerance=1e-9)
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
    camera = Camera(shape, solved.params[best], bool(mirrors[best]))
    return MaskFit(camera, camera.named_keypoints(), float(solved.cost[best]), *agreement(mask, shape, camera))


def agreement(mask: np.ndarray, shape: Shape, camera: Camera) -> tuple[float, float]:
    """IoU of the camera's silhouette with the mask, and the share of mask pixels it misses."""
    from shared.raster import rasterize

    model = rasterize(shape, camera.keypoints(), mask.shape[0])
    m = mask.astype(bool)
    inter = np.logical_and(model, m).sum()
    return float(inter / max(np.logical_or(model, m).sum(), 1)), float(1 - inter / max(m.sum(), 1))


# --- shape selection -----------------------------------------------------------------------

RICHER_MARGIN = 0.01  # IoU a twobox must gain over the box: it can always mimic a box


def select(fits: dict[str, MaskFit]) -> str:
    """Box or twobox from the fitted cuboids: the simpler shape unless the twobox explains the
    mask clearly better (higher IoU by RICHER_MARGIN and fewer missed building pixels)."""
    if "twobox" not in fits or "box" not in fits:
        return next(iter(fits))
    box, two = fits["box"], fits["twobox"]
    return "twobox" if two.iou > box.iou + RICHER_MARGIN and two.missed <= box.missed + 0.005 else "box"
