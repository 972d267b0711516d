"""Where a fit's error is (the issue "A real cuboid", Must have 7): corner error split into
the corners the true outline shows (vertices of the true silhouette's convex hull) and the
interior ones it hides, NME as a share of the building's image span, the relative error of
depth/height and width/height, the yaw error and the 3D IoU of the box up to scale.

Hidden corners carry most of the error (measured on main, 25 box masks a scene: hull
3.0-9.2 px mean, interior 10.3-21.5 px), so one mean hides where a fit can improve.

The 3D figures compare a fitted camera (`geometry.CameraParams`: a cuboid fit's own, or the
networks' corners lifted by `lift.lift`: they have no box of their own) with the truth's
(`geometry.from_sample_params` of a generated sample's `params`):

* yaw: the record's `yaw_deg` (`geometry.describe`: the camera-frame rotation is
  Rz(roll) Rx(pitch) Ry(yaw), camera tilt included, so the truth's is its describe()d yaw,
  not `params["yaw_deg"]`, which is taken before the camera's tilt). A `mirror`ed
  description poses the reflected solid, which is the same solid seen at -yaw (F Ry(y) F =
  Ry(-y)), so both are compared as solids: -yaw where mirrored. A box, and the face normals
  of a twobox, are the same under a half turn about the vertical, and a fit may name
  its sides either way (`CameraParams.naming`): the error is taken modulo 180 degrees,
  in [0, 90].
* 3D IoU up to scale (Objectron's measure, `iou3d`): both solids in camera coordinates,
  the fit scaled about the camera centre (which leaves its picture unchanged) so that its
  centre's depth equals the truth's. A monocular fit knows distance only in units of its
  own size, and this normalisation keeps the truth's distance, so the fit's size then
  follows from its focal length and picture: an error of focal length shows as an error
  of size (a weak-perspective fit, infinitely far, is a point at the truth's depth: IoU 0).
  The centre is the solid's centroid (a twobox's parts weighted by volume).
* focal length: its relative error, which explains most of a low 3D IoU (`focal_error`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from cuboidtrain.geometry.camera_params import (CameraParams, Spread, canonical, euler_angles, from_sample_params,
                                         rotation_matrices)
from cuboidtrain.geometry.intrinsics import KnownCamera
from cuboidtrain.geometry.iou3d import OrientedBox, union_iou
from cuboidtrain.geometry.lift import lift
from shared.shapes import Shape, get_shape

HULL_TOLERANCE_PX = 0.25  # a corner this close to a hull vertex is one (collinear hull edges)


def hull_corners(truth: np.ndarray, tolerance: float = HULL_TOLERANCE_PX) -> np.ndarray:
    """(N,) bool: which true corners are vertices of the true keypoints' convex hull (the
    silhouette's hull: a union of convex parts has the hull of all its corners)."""
    hull = cv2.convexHull(truth.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    return np.array([np.linalg.norm(hull - p, axis=1).min() <= tolerance for p in truth])


@dataclass(frozen=True)
class CornerErrors:
    """One fit's errors against its truth."""

    hull: np.ndarray  # (H,) px, corners on the true hull
    interior: np.ndarray  # (N - H,) px, the others
    nme: float  # mean corner error / the true keypoints' longer bounding-box side
    depth_height: np.ndarray  # relative error per part, |fit / true - 1|
    width_height: np.ndarray
    yaw_deg: float = math.nan  # `yaw_error_deg`; NaN without a true camera
    iou3d: float = math.nan  # `iou_up_to_scale`; NaN without a true camera
    focal: float = math.nan  # `focal_error`; NaN without a true camera, or for a weak-perspective fit
    # |error| / sd of every value the fit gave an error bar for (ratios, yaw, the focal length where
    # fitted: `camera.Spread`), against the truth: calibrated error bars hold two thirds within 1
    z_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # The fitted box's nearest corner's depth over its centre's (`CameraParams.nearest_depth`): at or below 0 a
    # corner is at or behind the camera, which then stands inside or behind the building; NaN
    # without a true camera (as the 3D figures).
    nearest_depth: float = math.nan


@dataclass(frozen=True)
class Truth:
    """What a generated sample says a fit should be: keypoints (N, 2) px, the nested ratios, and
    its camera (None for a sample whose params do not pose it)."""

    shape: Shape
    keypoints: np.ndarray
    ratios: dict
    camera: CameraParams | None

    @classmethod
    def of_sample(cls, sample) -> Truth:
        """A `shared.sample.Sample`'s truth, in its own px."""
        shape = get_shape(sample.shape)
        try:
            camera = from_sample_params(shape, sample.params)
        except (KeyError, TypeError, ValueError):  # another writer's sample, without the generator's params
            camera = None
        return cls(shape, np.asarray(sample.keypoints, dtype=np.float64), sample.ratios, camera)

    def known_camera(self) -> KnownCamera | None:
        """The focal length and principal point the generator framed the sample with, in its px."""
        if self.camera is None:
            return None
        return KnownCamera(self.camera.focal_px(), (float(self.camera.vector[9]), float(self.camera.vector[10])))


def corner_errors(shape: Shape, keypoints: np.ndarray, truth: np.ndarray, ratios: dict, true_ratios: dict) -> CornerErrors:
    """Score one fit (keypoints in the truth's px, `ratios` in the record's nested layout)."""
    error = np.linalg.norm(np.asarray(keypoints, dtype=np.float64) - truth, axis=1)
    on_hull = hull_corners(truth)
    span = float(np.ptp(truth, axis=0).max())
    relative = np.abs(shape.ratio_vector(ratios) / shape.ratio_vector(true_ratios) - 1)
    return CornerErrors(error[on_hull], error[~on_hull], float(error.mean()) / span, relative[0::2], relative[1::2])


def against_truth(keypoints: np.ndarray, ratios: dict, truth: Truth, camera: CameraParams | None = None,
          spread: Spread | None = None) -> CornerErrors:
    """All the figures of one fit against its truth. `camera`: the fit's cuboid (a cuboid fit's
    `CuboidFit.camera`); None for the networks' corners alone, which are then lifted
    (`lift.lift`, its defaults) to get a yaw and a box. `spread`: the fit's error bars."""
    errors = corner_errors(truth.shape, keypoints, truth.keypoints, ratios, truth.ratios)
    if truth.camera is None:
        return errors
    if camera is None:
        camera = lift(np.asarray(keypoints, dtype=np.float64), truth.shape).camera
    yaw = yaw_error_deg(camera, truth.camera)
    z_scores = np.zeros(0) if spread is None else _z_scores(ratios, truth, camera, yaw, spread)
    return replace(errors, yaw_deg=yaw, iou3d=iou_up_to_scale(camera, truth.camera),
                   focal=focal_error(camera, truth.camera), z_scores=z_scores, nearest_depth=camera.nearest_depth())


def _z_scores(ratios: dict, truth: Truth, camera: CameraParams, yaw_deg: float, spread: Spread) -> np.ndarray:
    """|error| / sd of each ratio, the yaw and (where fitted) the focal length."""
    shape = truth.shape
    z = list(np.abs(shape.ratio_vector(ratios) - shape.ratio_vector(truth.ratios)) / spread.ratios)
    z.append(yaw_deg / spread.yaw_deg)
    if spread.focal_px is not None and math.isfinite(camera.focal_px()):
        z.append(abs(camera.focal_px() - truth.camera.focal_px()) / spread.focal_px)
    return np.array(z)


def focal_error(camera: CameraParams, truth: CameraParams) -> float:
    """|fitted focal length / true - 1|; NaN for a weak-perspective fit (infinitely long focal
    length). What most often sinks the 3D IoU: a near-frontal view leaves the focal length and
    the box's size across the view nearly free together (the size follows the focal length at
    the truth's depth)."""
    fitted = camera.focal_px()
    return abs(fitted / truth.focal_px() - 1) if math.isfinite(fitted) else math.nan


def solid_yaw_deg(camera: CameraParams) -> float:
    """The yaw of the solid a camera poses, in degrees: the yaw of its rotation R (camera =
    R F X + T, F the mirror), which is the record's `yaw_deg` (`describe`) negated where
    mirrored: the record poses F R F (see the module's notes)."""
    vector, _ = canonical(camera.vector, camera.mirror)
    return euler_angles(rotation_matrices(vector[None, 2:5])[0])[1]


def yaw_error_deg(camera: CameraParams, truth: CameraParams) -> float:
    """|yaw difference| of the two solids modulo a half turn, in [0, 90] degrees."""
    difference = (solid_yaw_deg(camera) - solid_yaw_deg(truth)) % 180.0
    return float(min(difference, 180.0 - difference))


def camera_boxes(camera: CameraParams) -> list[OrientedBox] | None:
    """The parts of the solid a camera poses, in camera coordinates (x right, y down, z forward;
    units: the height of the only / RIGHT part); None for a weak-perspective camera (k <= 0:
    infinitely far)."""
    camera = CameraParams(camera.shape, *canonical(camera.vector, camera.mirror))
    if camera.weak:
        return None
    points = camera.camera_points()
    return [OrientedBox.from_corners(points[list(part)]) for part in camera.shape.parts]


def centroid(boxes: list[OrientedBox]) -> np.ndarray:
    """The solid's centre of volume."""
    volumes = np.array([b.volume for b in boxes])
    centres = np.array([b.centre for b in boxes])
    if volumes.sum() <= 0:  # a degenerate fit (a flat box): the parts' plain mean
        return centres.mean(0)
    return (volumes[:, None] * centres).sum(0) / volumes.sum()


def iou_up_to_scale(camera: CameraParams, truth: CameraParams) -> float:
    """3D IoU of the solid `camera` poses with the truth's, the fit scaled about the camera
    centre so that its centroid's depth is the truth's (see the module's notes)."""
    fitted, true = camera_boxes(camera), camera_boxes(truth)
    if true is None:
        raise ValueError("the true camera is weak-perspective: no depth to scale a fit to")
    if fitted is None:
        return 0.0
    depth = centroid(fitted)[2]
    if not depth > 0:  # behind the camera: no picture of it
        return 0.0
    factor = centroid(true)[2] / depth
    return union_iou([b.scaled(factor) for b in fitted], true)


def summarise(errors: list[CornerErrors]) -> dict[str, float]:
    """Means and medians over many fits (corners pooled; ratios pooled over parts; yaw, 3D IoU
    and focal length over the fits that have them, `posed` counting those with a true camera;
    NaN where there is none)."""
    pooled = {name: np.concatenate([getattr(e, name) for e in errors]) if errors else np.zeros(0)
              for name in ("hull", "interior", "depth_height", "width_height")}
    nme = np.array([e.nme for e in errors])
    out = {}
    for name in ("hull", "interior"):
        out[f"{name}_mean_px"], out[f"{name}_median_px"] = _mean_median(pooled[name])
    out["interior_share"] = len(pooled["interior"]) / max(len(pooled["hull"]) + len(pooled["interior"]), 1)
    out["nme_mean"], out["nme_median"] = _mean_median(nme)
    for name in ("depth_height", "width_height"):
        out[f"{name}_mean_rel"], out[f"{name}_median_rel"] = _mean_median(pooled[name])
    yaw, iou3d, focal = (np.array([getattr(e, name) for e in errors]) for name in ("yaw_deg", "iou3d", "focal"))
    out["posed"] = int(np.isfinite(iou3d).sum())
    out["yaw_mean_deg"], out["yaw_median_deg"] = _mean_median(yaw[np.isfinite(yaw)])
    out["iou3d_mean"], out["iou3d_median"] = _mean_median(iou3d[np.isfinite(iou3d)])
    out["focal_mean_rel"], out["focal_median_rel"] = _mean_median(focal[np.isfinite(focal)])
    z_scores = np.concatenate([e.z_scores for e in errors]) if errors else np.zeros(0)
    out["within_1sd"], out["within_2sd"] = ((float(np.mean(z_scores <= n)) if len(z_scores) else float("nan"))
                                            for n in (1, 2))
    nearest = np.array([e.nearest_depth for e in errors])
    nearest = nearest[np.isfinite(nearest)]
    out["camera_inside"] = int((nearest <= 0).sum())  # fits (or networks' corners lifted) with a corner at or behind the camera
    out["nearest_depth_min"] = float(nearest.min()) if len(nearest) else float("nan")
    return out


def _mean_median(values: np.ndarray) -> tuple[float, float]:
    return (float(np.mean(values)), float(np.median(values))) if len(values) else (float("nan"), float("nan"))
