"""The fitted cuboid's camera parameterisation: a parameter vector, its projection, and
its meaning in shared/camera.py's terms (a `Cuboid` posed before an `Intrinsics`).

shared/camera.py is the model the generator draws from: extents, a pose and a pinhole
camera. Fitting needs the same model written so that a solver can walk it smoothly,
batched over hypotheses, hence a vector (one row per hypothesis, float64):

    0 log width   1 log depth          (height of the only / RIGHT part is 1: the scale gauge)
    2..4 rotation vector (object -> camera, OpenCV camera: x right, y down, z forward)
    5, 6 tx, ty   object-centre offset in height units
    7 log s       px per height unit at the centre's depth (= f / tz)
    8 k           1 / tz, perspective strength (0 = weak perspective)
    9, 10 cx, cy  principal point, px
    twobox only: 11 split (share of the width taken by the RIGHT part), 12 log hL (LEFT part's height)

    u = c + s * (R X + t)_xy / (1 + k (R X)_z)

This is the pinhole u = c + f (R X + T)_xy / (R X + T)_z with T = (tx, ty, 1/k), f = s / k,
rewritten so that weak perspective (k -> 0) is an ordinary point rather than infinity: the
solver walks through near-affine views without the focal/distance blow-up. A discrete
`mirror` flag reflects the object in x before the rotation: viewer naming (LEFT = image-left,
FRONT = nearer) can make the labelled corners a reflected box, which no rotation reaches.

Measured on the generator's own views (docs/research/geometric-fit, 2000 views per
scene and shape): projection equal to the samples' keypoints to 3e-12 px.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import cv2
import numpy as np

from shared.camera import Cuboid, Extents, Intrinsics, Pose, viewer_order
from shared.shapes import Shape, get_shape

NUM_PARAMS = {1: 11, 2: 13}  # by number of parts
WEAK_K = 1e-9  # k at or below this is weak perspective: no finite focal length
CORNER_SIDES = np.array([[(c >> 1) & 1, c & 1, (c >> 2) & 1] for c in range(8)], dtype=np.float64)  # left, bottom, front
MIRROR_X = np.diag([-1.0, 1.0, 1.0])
EYE3 = np.eye(3)
EYE3.flags.writeable = False  # shared by every caller


@lru_cache(maxsize=None)
def object_basis(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    """Object corners as an affine map of theta = (w, d) for box, (w, d, m, hL) for twobox:
    X = coef @ theta + const, coef (N, 3, Q), const (N, 3), in Table 1's corner order (m is
    the x of the plane between the parts, hL the LEFT part's height). Height of the only /
    RIGHT part is 1. Every coefficient is 0, +-1/2 or +-1, so the product is exact."""
    n, q = shape.num_keypoints, 2 * len(shape.parts)
    coef, const = np.zeros((n, 3, q)), np.zeros((n, 3))
    for index, part in enumerate(shape.parts):
        for c, corner in enumerate(part):
            left, bottom, front = CORNER_SIDES[c]
            coef[corner, 2, 1] = 0.5 - front  # z = -d/2 front, +d/2 back
            if index == 0:  # the only part, or the RIGHT one: x from m (or -w/2) to w/2
                coef[corner, 0, 0] = 0.5 if not left else (0.0 if q == 4 else -0.5)
                if left and q == 4:
                    coef[corner, 0, 2] = 1.0
                const[corner, 1] = bottom - 0.5
            else:  # LEFT part: x from -w/2 to m, top at 1/2 - hL
                coef[corner, 0, 0] = -0.5 if left else 0.0
                coef[corner, 0, 2] = 0.0 if left else 1.0
                const[corner, 1] = 0.5
                coef[corner, 1, 3] = 0.0 if bottom else -1.0
    coef.flags.writeable = const.flags.writeable = False  # shared by every caller
    return coef, const


def stack_last(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """np.stack(arrays, axis=-1) of arrays of one shape, without its wrapper (several µs a call, paid
    at every step of every solver): the same values."""
    stacked = np.empty((*arrays[0].shape, len(arrays)), dtype=np.result_type(*arrays))
    for k, array in enumerate(arrays):
        stacked[..., k] = array
    return stacked


def object_points(params: np.ndarray, shape: Shape, mirror: np.ndarray) -> np.ndarray:
    """(B, N, 3) labelled object corners for (B, P) params; `mirror` (B,) bool reflects x."""
    coef, const = object_basis(shape)
    w, d = np.exp(params[:, 0]), np.exp(params[:, 1])
    theta = [w, d] if len(shape.parts) == 1 else [w, d, w / 2 - params[:, 11] * w, np.exp(params[:, 12])]
    n, q = len(const), coef.shape[2]
    points = (stack_last(theta) @ coef.reshape(n * 3, q).T).reshape(-1, n, 3) + const
    if mirror.any():  # (x 1 is exact: rows not mirrored are as they were)
        points[..., 0] *= np.where(mirror, -1.0, 1.0)[:, None]
    return points


def rotation_matrices(rotvec: np.ndarray) -> np.ndarray:
    """(B, 3) rotation vectors -> (B, 3, 3) matrices (Rodrigues, stable near 0)."""
    return _rodrigues(rotvec)[0]


def _rodrigues(rotvec: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`rotation_matrices`, with what the rotation's derivatives read too (`_rotation_columns`): each
    vector's squared length (B,) and cross-product matrix (B, 3, 3), computed once for both."""
    squared_length = (rotvec * rotvec).sum(1)
    theta = np.sqrt(squared_length)
    small = theta < 1e-8
    if small.any():
        safe = np.where(small, 1.0, theta)
        squared = theta**2
        a = np.where(small, 1.0 - squared / 6, np.sin(theta) / safe)
        b = np.where(small, 0.5 - squared / 24, (1 - np.cos(theta)) / safe**2)
    else:  # no rotation near 0 (nearly always): the same values, without the series' arrays
        a, b = np.sin(theta) / theta, (1 - np.cos(theta)) / theta**2
    k = _skew(rotvec)
    return EYE3 + a[:, None, None] * k + b[:, None, None] * (k @ k), squared_length, k


def rotation_vector(matrix: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(matrix, dtype=np.float64))[0].ravel()


def rotated_points(params: np.ndarray, shape: Shape, mirror: np.ndarray) -> np.ndarray:
    """(B, N, 3) corners rotated into the camera, object centre at the origin (not translated)."""
    return object_points(params, shape, mirror) @ rotation_matrices(params[:, 2:5]).transpose(0, 2, 1)


def _flags(mirror, rows: int) -> np.ndarray:
    """(rows,) bool mirror flags from one flag or (rows,) of them (np.broadcast_to only where needed:
    the solvers pass (rows,) at every step, and its wrapper costs more than the projection's products)."""
    mirror = np.asarray(mirror, dtype=bool)
    return mirror if mirror.shape == (rows,) else np.broadcast_to(mirror, (rows,))


def project(params: np.ndarray, shape: Shape, mirror) -> np.ndarray:
    """(B, P) or (P,) params -> (B, N, 2) or (N, 2) image points, in the model's corner labels."""
    params = np.asarray(params)
    single = params.ndim == 1
    params = params[None] if single else params
    mirror = _flags(mirror, len(params))
    rotated = rotated_points(params, shape, mirror)
    depth = 1.0 + params[:, 8, None] * rotated[..., 2]
    xy = (rotated[..., :2] + params[:, None, 5:7]) * (np.exp(params[:, 7])[:, None, None] / depth[..., None])
    image = xy + params[:, None, 9:11]
    return image[0] if single else image


def project_with_jacobian(params: np.ndarray, shape: Shape, mirror) -> tuple[np.ndarray, np.ndarray]:
    """(B, N, 2) image points and their analytic Jacobian (B, N, 2, P) with respect to (B, P)
    params: the solver's derivatives, exact where forward differences lose half the digits
    (flat valleys of near-frontal views need them) and one evaluation instead of P + 1."""
    image, jacobian = project_deferred(params, shape, mirror)
    return image, jacobian()


def project_deferred(params: np.ndarray, shape: Shape, mirror) -> tuple[np.ndarray, Callable[[], np.ndarray]]:
    """`project_with_jacobian`'s image points, and a function of no arguments that computes its Jacobian
    from what they left: for a solver that needs it only for the steps it takes (the same numbers)."""
    params = np.asarray(params)
    params = params[None] if params.ndim == 1 else params
    b, p = params.shape
    mirror = _flags(mirror, b)
    objects = object_points(params, shape, mirror)  # (B, N, 3)
    rot, squared_length, skew = _rodrigues(params[:, 2:5])
    rotated = objects @ rot.transpose(0, 2, 1)
    s, k = np.exp(params[:, 7])[:, None], params[:, 8, None]
    den = 1.0 + k * rotated[..., 2]  # (B, N)
    scale = s / den  # d u / d (R X)'s x, y
    offset = (rotated[..., :2] + params[:, None, 5:7]) * scale[..., None]  # u - c
    image = offset + params[:, None, 9:11]

    def jacobian() -> np.ndarray:
        jac = np.zeros((b, objects.shape[1], 2, p))
        # d u / d (R X): s / den on x, y; -(u - c) k / den on z.
        d_rotated = np.zeros((b, objects.shape[1], 2, 3))
        d_rotated[..., 0, 0] = d_rotated[..., 1, 1] = scale
        d_rotated[..., 2] = -offset * (k / den)[..., None]
        d_object = d_rotated @ rot[:, None]  # (B, N, 2, 3): through R
        # Object coordinates: every x scales with w (log w), every z with d (log d).
        jac[..., 0] = d_object[..., 0] * objects[..., None, 0]
        jac[..., 1] = d_object[..., 2] * objects[..., None, 2]
        jac[..., 2:5] = _rotation_columns(d_object, params[:, 2:5], objects, rot, squared_length, skew)
        jac[..., 0, 5] = jac[..., 1, 6] = scale
        jac[..., 7] = offset
        jac[..., 8] = -offset * (rotated[..., 2] / den)[..., None]
        jac[..., 0, 9] = jac[..., 1, 10] = 1.0
        if len(shape.parts) == 2:
            sign = np.where(mirror, -1.0, 1.0)[:, None]
            w, h_left = np.exp(params[:, 0])[:, None], np.exp(params[:, 12])[:, None]
            middle, top_left = _split_corners(shape)
            jac[..., 11] = d_object[..., 0] * np.where(middle, -w * sign, 0.0)[..., None]
            jac[..., 12] = d_object[..., 1] * np.where(top_left, -h_left, 0.0)[..., None]
        return jac

    return image, jacobian


@lru_cache(maxsize=None)
def _split_corners(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool each, for a two-part shape: the corners on the wall between the parts (x =
    middle, moved by the split) and the LEFT part's top corners (y = 1/2 - hL). Fixed per shape:
    computed once, not on every solver iteration."""
    middle, top_left = np.zeros(shape.num_keypoints, dtype=bool), np.zeros(shape.num_keypoints, dtype=bool)
    for c, corner in enumerate(shape.parts[0]):
        middle[corner] |= bool(CORNER_SIDES[c, 0])  # the RIGHT part's LEFT corners: x = middle
    for c, corner in enumerate(shape.parts[1]):
        middle[corner] |= not CORNER_SIDES[c, 0]
        top_left[corner] |= not CORNER_SIDES[c, 1]  # the LEFT part's top: y = 1/2 - hL
    middle.flags.writeable = top_left.flags.writeable = False  # shared by every caller
    return middle, top_left


def _rotation_columns(d_object: np.ndarray, rotvec: np.ndarray, objects: np.ndarray, rot: np.ndarray,
                      theta2: np.ndarray, skew_w: np.ndarray) -> np.ndarray:
    """(B, N, 2, 3): d u / d w, the image points' derivatives by the rotation vectors (B, 3) (their
    squared lengths `theta2` (B,) and cross-product matrices `skew_w` (B, 3, 3): `_rodrigues`), from
    their derivatives by the object points (B, N, 2, 3) (d u / d (R X) @ R) at points X (B, N, 3).

    Gallego & Yezzi (2015): d(R v)/dw = -R [v]x (w w^T + (R^T - I)[w]x) / |w|^2, and -[v]x at w = 0
    (where R is I): d u / d w = -(d u / d X) [X]x M, M the bracket over |w|^2 (I at w = 0), two
    small products a point instead of three."""
    small = theta2 < 1e-16
    near_zero = small.any()
    safe = np.where(small, 1.0, theta2) if near_zero else theta2
    inner = (rotvec[:, :, None] * rotvec[:, None, :] + (rot.transpose(0, 2, 1) - EYE3) @ skew_w) / safe[:, None, None]
    if near_zero:
        inner[small] = EYE3
    return -(d_object @ _skew(objects)) @ inner[:, None]


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]x: one product with a fixed sign table
    (exact: every entry is +-1 or 0), a quarter of the cost of stacking nine arrays."""
    return (v @ SKEW_TABLE).reshape(*v.shape[:-1], 3, 3)


SKEW_TABLE = np.zeros((3, 9))  # row k: where v_k goes in [v]x, flattened
for _k, _at, _sign in ((2, 1, -1.0), (1, 2, 1.0), (2, 3, 1.0), (0, 5, -1.0), (1, 6, -1.0), (0, 7, 1.0)):
    SKEW_TABLE[_k, _at] = _sign


def ratios(params: np.ndarray, shape: Shape) -> np.ndarray:
    """(B, 2 or 4) ratios in `shape.ratio_names` order (depth/height, width/height per part)."""
    params = np.atleast_2d(params)
    w, d = np.exp(params[:, 0]), np.exp(params[:, 1])
    if len(shape.parts) == 1:
        return stack_last([d, w])
    split, h_left = params[:, 11], np.exp(params[:, 12])
    return stack_last([d, split * w, d / h_left, (1 - split) * w / h_left])


def log_ratio_jacobian(params: np.ndarray, shape: Shape) -> np.ndarray:
    """(B, 2 or 4, P): d log(ratios) / d params, `ratios`' order."""
    params = np.atleast_2d(params)
    jac = np.zeros((len(params), 2 * len(shape.parts), params.shape[1]))
    jac[:, 0, 1] = 1.0  # log d
    jac[:, 1, 0] = 1.0  # log w (+ log split for twobox)
    if len(shape.parts) == 2:
        split = params[:, 11]
        jac[:, 1, 11] = 1 / split
        jac[:, 2, 1], jac[:, 2, 12] = 1.0, -1.0  # log d - log hL
        jac[:, 3, 0], jac[:, 3, 11], jac[:, 3, 12] = 1.0, -1 / (1 - split), -1.0
    return jac


def canonical(vector: np.ndarray, mirror: bool) -> tuple[np.ndarray, bool]:
    """The same projection with k >= 0. A mirrored object seen with k < 0 is the depth-reversed
    (Necker) twin of a camera in front of the object: R F_m X and D R F F_m X differ only in z's
    sign (D = diag(1, 1, -1)), and k -> -k undoes it, for every point, not just the corners."""
    if vector[8] >= 0:
        return vector, mirror
    rot = np.diag([1.0, 1.0, -1.0]) @ rotation_matrices(vector[None, 2:5])[0] @ MIRROR_X
    twin = vector.copy()
    twin[2:5], twin[8] = rotation_vector(rot), -vector[8]
    return twin, not mirror


@dataclass(frozen=True)
class CameraParams:
    """One parameter vector (layout above) and its reflection flag: a fitted or generated cuboid. A value:
    its vector is not changed once it is made (its projection and naming are computed once, on first use)."""

    shape: Shape
    vector: np.ndarray  # (P,)
    mirror: bool

    def keypoints(self) -> np.ndarray:
        """(N, 2) px in the model's corner labels (what the solver matched)."""
        return self._keypoints.copy()

    @cached_property
    def _keypoints(self) -> np.ndarray:
        return project(self.vector, self.shape, self.mirror)

    def nearest_depth(self) -> float:
        """The nearest corner's depth as a share of the box centre's (1 + k z, the projection's own
        denominator): 1 for a far camera, at or below 0 where a corner is at or behind it (the
        camera inside or behind the box)."""
        rotated = rotated_points(self.vector[None], self.shape, np.array([self.mirror]))[0]
        return float((1.0 + self.vector[8] * rotated[:, 2]).min())

    def naming(self) -> np.ndarray:
        """The index order that renames the model's corners by shared.camera's viewer rules
        (a fit may have drifted past a side): `keypoints()[naming()]` are viewer-named."""
        return self._naming.copy()

    @cached_property
    def _naming(self) -> np.ndarray:
        rotated = rotated_points(self.vector[None], self.shape, np.array([self.mirror]))[0]
        # Only z differences (FRONT/BACK) and image x (LEFT/RIGHT) matter: the translation can stay out.
        return viewer_order(self.shape, rotated, self._keypoints).order

    def named_keypoints(self) -> np.ndarray:
        return self.keypoints()[self.naming()]

    def ratios(self) -> np.ndarray:
        return ratios(self.vector, self.shape)[0]

    @property
    def weak(self) -> bool:
        """Weak perspective (k <= 0, to rounding): the camera is infinitely far, no focal length."""
        return bool(self.vector[8] <= WEAK_K)

    def camera_points(self, distance: float | None = None) -> np.ndarray:
        """(N, 3) corners in the camera's frame (x right, y down, z forward), in the model's
        corner labels and height units of the only / RIGHT part: R F X + (tx, ty, 1/k).
        `distance` stands in for 1/k (a weak-perspective camera has none)."""
        p = self.vector
        rotated = rotated_points(p[None], self.shape, np.array([self.mirror]))[0]
        return rotated + np.array([p[5], p[6], 1.0 / p[8] if distance is None else distance])

    def focal_px(self) -> float:
        """The record's `focal_px`: f = s / k of the k >= 0 twin (`canonical`), inf for weak perspective."""
        vector, _ = canonical(self.vector, self.mirror)
        return math.inf if vector[8] <= WEAK_K else float(math.exp(vector[7]) / vector[8])

    def pinhole(self) -> tuple[Cuboid, Intrinsics] | None:
        """The same cuboid in shared.camera's terms (height units of the taller part), or
        None for a weak-perspective fit (k <= 0: the camera is infinitely far)."""
        p, shape = self.vector, self.shape
        if self.weak:
            return None
        w, d = math.exp(p[0]), math.exp(p[1])
        rot = rotation_matrices(p[None, 2:5])[0]
        offset = np.array([p[5], p[6], 1.0 / p[8]])
        if len(shape.parts) == 1:
            height, extras = 1.0, {}
        else:
            h_left = math.exp(p[12])
            height = max(1.0, h_left)
            extras = dict(split=float(p[11]), height_ratio=min(1.0, h_left) / height, left_taller=h_left > 1.0)
            # shared.camera stands both parts on y = height / 2; this model on y = 1 / 2.
            offset = offset - rot @ np.array([0.0, height / 2 - 0.5, 0.0])
        if self.mirror:  # here camera = R F X + T; shared's flip is camera = F (L X + o): L = F R F, o = F T
            rot, offset = MIRROR_X @ rot @ MIRROR_X, MIRROR_X @ offset
        pitch, yaw, roll = euler_angles(rot)
        scale = height  # shared.camera's units: the taller part is 1 high
        extents = Extents(w / scale, 1.0, d / scale, **extras)
        pose = Pose(pitch, yaw, roll, offset[0] / scale, offset[1] / scale, offset[2] / scale, 0.0, self.mirror)
        return Cuboid(extents, pose), Intrinsics(focal=float(math.exp(p[7]) / p[8]), principal=(float(p[9]), float(p[10])))


def euler_angles(rot: np.ndarray) -> tuple[float, float, float]:
    """(pitch, yaw, roll) in degrees with rot = Rz(roll) Rx(pitch) Ry(yaw): the inverse of
    shared.camera.rotation (its third row is (-cos p sin y, sin p, cos p cos y))."""
    pitch = math.asin(float(np.clip(rot[2, 1], -1.0, 1.0)))
    yaw = math.atan2(-rot[2, 0], rot[2, 2])
    roll = math.atan2(-rot[0, 1], rot[1, 1])
    return math.degrees(pitch), math.degrees(yaw), math.degrees(roll)


def from_sample_params(shape: Shape, params: dict) -> CameraParams:
    """The parameters whose projection, in the shape's labels, equals a generated sample's
    keypoints (its `params`: Cuboid.from_params, frame_scale / frame_origin, the swaps).

    The generator poses the object (tilt and flip included: `Pose.transform`) and names the
    corners after projection; the named corners are the object's reflected by
    G = diag(+-1, 1, +-1). M = L G is then a rotation or a reflection, and a reflection is a
    rotation of the x-mirrored object."""
    cuboid = Cuboid.from_params(params)
    linear, offset = (np.array(a) for a in cuboid.pose.transform())
    sx, sz = (-1.0 if params["swap_left_right"] else 1.0), (-1.0 if params["swap_front_back"] else 1.0)
    m = linear @ np.diag([sx, 1.0, sz])
    mirror = bool(np.linalg.det(m) < 0)
    rot = m @ MIRROR_X if mirror else m
    e = cuboid.extents
    if len(shape.parts) == 1:
        scale, shift, extra = e.height, np.zeros(3), []
    else:
        low = e.height * e.height_ratio
        h_left, h_right = (e.height, low) if e.left_taller else (low, e.height)
        split = e.split
        if params["swap_left_right"]:
            split, h_left, h_right = 1 - split, h_right, h_left
        scale, shift = h_right, np.array([0.0, e.height / 2 - h_right / 2, 0.0])  # ground: h/2 there, 1/2 here
        extra = [split, math.log(h_left / h_right)]
    t = (offset + m @ shift) / scale  # camera = scale * (rot X_model + t)
    intrinsics = Intrinsics.from_params(params)
    vector = np.array([math.log(e.width / scale), math.log(e.depth / scale), *rotation_vector(rot), t[0], t[1],
                       math.log(intrinsics.focal / t[2]), 1.0 / t[2], *intrinsics.principal, *extra])
    return CameraParams(shape, vector, mirror)


@dataclass(frozen=True)
class Evidence:
    """What a mask fit shows of its own error beyond the Laplace sd, in % of the frame's longer side
    (`cuboidtrain.geometry.uncertainty` reads it)."""

    outline_rms: float  # the outline's rms residual at the solution (`CuboidFit.residual_px`)
    corner_gap: float  # the network's corners' rms distance from the fitted box's, weighted by confidence
    # How far apart the lift's starts put the focal length (the range of their log focal lengths):
    # where the corners admit several cameras, the one the fit settled on is the less certain
    start_spread: float = 0.0
    # The silhouette's size in px (its bounding box's longer side): a small mask's error bars are
    # widened (`uncertainty.inflation`); inf: never
    silhouette_px: float = math.inf


@dataclass(frozen=True)
class Spread:
    """A fit's standard deviations in the record's terms (`cuboidtrain.geometry.uncertainty`)."""

    ratios: np.ndarray  # (R,) in `shape.ratio_names` order, in the ratios' own units
    yaw_deg: float
    focal_px: float | None  # None where the focal length is given, or infinite (weak perspective)
    # What they were calibrated from (benchmarks/calibration/bench_coverage.py refits the calibration on them):
    # each quantity's features (`uncertainty.features`), ratios first, then the yaw and the focal length
    features: np.ndarray | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class CuboidFit:
    """A cuboid that explains a mask (or corners), in the record's terms: input px and degrees."""

    shape: str
    keypoints: np.ndarray  # (N, 2) input px, viewer-named: the fitted cuboid's projection
    ratios: dict[str, float]  # the cuboid's own geometry, `Shape.ratio_dict` layout
    yaw_deg: float  # rotation relative to the camera, shared.camera.rotation's convention
    pitch_deg: float
    roll_deg: float
    focal_px: float  # inf for a weak-perspective fit
    principal_px: tuple[float, float]
    mirror: bool  # the labelled corners are a reflected box
    on_outline: np.ndarray  # (N,) bool, viewer-named: the corner is a vertex of the fitted silhouette's outline
    iou: float | None  # the fitted silhouette's IoU with the input mask; None for a lift of corners alone
    residual_px: float  # rms distance the objective left (corners for a lift, the outline for a mask fit)
    camera: CameraParams  # the parameter vector, for a caller that fits on from here
    spread: Spread | None = None  # the error bars, where the solver gave them (a mask fit)
    unexplained: float | None = None  # the share of the mask's pixels the silhouette leaves out; None: a lift


def describe(camera: CameraParams, residual_px: float, iou: float | None = None,
             unexplained: float | None = None) -> CuboidFit:
    """The record's view of fitted parameters: named keypoints, ratios, angles, intrinsics, flags."""
    shape = camera.shape
    vector, mirror = canonical(camera.vector, camera.mirror)
    if vector is not camera.vector:  # the k >= 0 twin; else the camera itself, its projection computed once
        camera = CameraParams(shape, vector, mirror)
    order = camera.naming()
    pinhole = camera.pinhole()
    if pinhole is None:
        angles = euler_angles(rotation_matrices(camera.vector[None, 2:5])[0])
        focal = math.inf
    else:
        cuboid, intrinsics = pinhole
        angles = (cuboid.pose.pitch_deg, cuboid.pose.yaw_deg, cuboid.pose.roll_deg)
        focal = intrinsics.focal
    keypoints = camera.keypoints()
    return CuboidFit(
        shape=shape.name, keypoints=keypoints[order], ratios=shape.ratio_dict(camera.ratios()),
        yaw_deg=angles[1], pitch_deg=angles[0], roll_deg=angles[2], focal_px=focal,
        principal_px=(float(camera.vector[9]), float(camera.vector[10])), mirror=camera.mirror,
        on_outline=outline_corners(shape, keypoints)[order], iou=iou, residual_px=residual_px, camera=camera,
        unexplained=unexplained)


def outline_corners(shape: Shape | str, keypoints: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """(N,) bool: which corners are vertices of the silhouette's outline, i.e. of their part's
    convex hull and not inside the other part. Those the outline determines; the rest are hidden."""
    shape = get_shape(shape) if isinstance(shape, str) else shape
    flags = np.zeros(len(keypoints), dtype=bool)
    hulls = [cv2.convexHull(keypoints[list(p)].astype(np.float32)) for p in shape.parts]
    for part, hull in zip(shape.parts, hulls):
        vertices = hull.reshape(-1, 2).astype(np.float64)
        gaps = keypoints[list(part)][:, None] - vertices[None]  # (8, V): np.linalg.norm's arithmetic, all at once
        on_hull = np.sqrt((gaps * gaps).sum(-1)).min(1) <= 1e-3
        for index, seen in zip(part, on_hull.tolist()):
            inside_other = any(cv2.pointPolygonTest(other, tuple(map(float, keypoints[index])), True) > tolerance
                               for other in hulls if other is not hull)
            flags[index] = seen and not inside_other
    return flags
