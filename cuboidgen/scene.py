"""Synthetic scenes: draw a box (or two) and a pose from a scene's ranges, then frame its
projection into the image.

The cuboid itself (extents, pose, perspective projection, naming in viewer terms) is
shared/camera.py's, the model a fit searches as well; this module only draws its
numbers (the paper's recipe, 3.3.1: a random non-uniform scale, rotation and translation)
and picks the pinhole camera (`frame`) that puts the silhouette in the picture.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cuboidgen.config import SceneConfig
from shared.camera import Cuboid, Intrinsics, name_corners, perspective
from shared.errors import UsageError
from shared.shapes import Shape

MIN_DEPTH = 0.05  # nearest corner's z as a fraction of the distance; closer draws are redrawn
MAX_DRAWS = 1000  # draws before a scene is refused (every preset's first draw is in front of the camera)


@dataclass(frozen=True)
class View:
    """A posed, projected, framed shape: what the rasteriser and the sample need."""

    keypoints: np.ndarray  # (N, 2) px, integer = pixel centre
    points3d: np.ndarray  # (N, 3) camera frame, same order as keypoints
    ratios: dict
    params: dict  # every value drawn, as plain floats


def uniform(rng: np.random.Generator, bounds) -> float:
    lo, hi = bounds
    return lo + (hi - lo) * rng.random()


def draw_view(shape: Shape, scene: SceneConfig, size: int, rng: np.random.Generator,
              beside: Callable[[np.ndarray], np.ndarray] | None = None) -> View:
    """Draw one view of `shape` from `scene`'s ranges, framed into a size x size image. `beside` maps the
    keypoints in the camera frame (viewer-named) to more camera-frame points the picture must hold as
    well (an irregular building's roof or neighbour: cuboidgen.irregular), framed with the shape."""
    for _ in range(MAX_DRAWS):
        params = draw_params(shape, scene, rng)
        cuboid = Cuboid.from_params(params)
        camera = cuboid.camera_points(shape)
        if camera[:, 2].min() > MIN_DEPTH * cuboid.pose.distance:
            break
    else:  # a scene whose boxes reach behind the camera: refused, not looped on forever
        raise UsageError(f"scene {scene.name!r}: {MAX_DRAWS} {shape.name} draws in a row came closer to the camera "
                         f"than {MIN_DEPTH:g} x distance: expected distance well beyond the extents")
    named = name_corners(shape, camera)
    params.update(named.naming.params())
    extra = beside(named.camera) if beside is not None else None
    outline = named.image if extra is None or not len(extra) else np.concatenate([named.image, perspective(extra)])
    intrinsics, margin = frame(outline, size, scene, rng)
    params["margin"] = margin
    params.update(intrinsics.params())
    return View(keypoints=named.keypoints(intrinsics), points3d=named.camera, ratios=shape.ratios(named.camera),
                params=params)


# The order the numbers are drawn in (one rng number each): reordering changes every sample.
_EXTENTS = ("width", "height", "depth")
_POSE = ("pitch_deg", "yaw_deg", "roll_deg", "offset_x", "offset_y", "distance", "camera_pitch_deg")


def draw_params(shape: Shape, scene: SceneConfig, rng: np.random.Generator) -> dict:
    """Every number of a cuboid (`shared.camera.Cuboid.from_params` reads them), drawn from `scene`'s ranges."""
    two = len(shape.parts) == 2
    # One call for every draw: the same numbers as one `rng.random()` each, in this order.
    draws = iter(rng.random(len(_EXTENTS) + 3 * two + len(_POSE) + (scene.eye_height is not None) + 1).tolist())

    def uniform_draw(bounds) -> float:
        lo, hi = bounds
        return lo + (hi - lo) * next(draws)

    p = {k: uniform_draw(getattr(scene, k)) for k in _EXTENTS}
    if two:
        p["split"] = uniform_draw(scene.split)
        p["height_ratio"] = uniform_draw(scene.height_ratio)
        p["left_taller"] = next(draws) < 0.5
    for k in _POSE:
        p[k] = uniform_draw(getattr(scene, k))
    if scene.eye_height is not None:
        # Standing on the ground: the centre sits half the height above it.
        p["eye_height"] = uniform_draw(scene.eye_height)
        p["offset_y"] = p["eye_height"] - p["height"] / 2
    p["flip"] = next(draws) < scene.flip_probability
    return p


def frame(image: np.ndarray, size: int, scene: SceneConfig, rng: np.random.Generator) -> tuple[Intrinsics, float]:
    """The pinhole camera, and the margin drawn, that frame image-plane points: the
    silhouette's longer side spans the image less two margins, centred with a small random
    shift (kept inside the image). Its focal length is the scale, its principal point the
    shift (the sample's `frame_scale`, `frame_origin`)."""
    draw, *shifts = rng.random(3).tolist()  # as three rng.random() calls
    margin = scene.margin[0] + (scene.margin[1] - scene.margin[0]) * draw
    xs, ys = image[:, 0].tolist(), image[:, 1].tolist()
    lo = (min(xs), min(ys))
    spans = (max(xs) - lo[0], max(ys) - lo[1])
    scale = size * (1 - 2 * margin) / max(spans)
    origin = []
    for low, span, draw in zip(lo, spans, shifts):
        slack = max(size - 1 - span * scale, 0.0)  # free room on this axis, in px
        jitter = (draw - 0.5) * scene.centre_jitter * min(slack, size * margin)
        origin.append(slack / 2 + jitter - low * scale)  # pixel centres: the image spans 0 .. size - 1
    return Intrinsics(focal=scale, principal=tuple(origin)), margin


def check_drawable(scene: SceneConfig, shapes, size: int, views: int = 16) -> None:
    """A few views of each shape drawn and framed, so a scene that cannot be drawn (its boxes
    behind the camera) is refused in one line at start-up, not in every worker."""
    rng = np.random.default_rng(0)
    for shape in shapes:
        for _ in range(views):
            draw_view(shape, scene, size, rng)
