"""Synthetic scenes: draw a box (or two), pose it, project it, name its corners in viewer terms.

The paper's recipe (3.3.1): a canonical box, a random non-uniform scale, rotation
and translation, then a perspective projection. Frames are:

* object: x toward the box's RIGHT, y down (BOTTOM), z away (BACK); centre at 0;
* camera: OpenCV's, x right, y down, z forward; the image is x/z, y/z before framing.

Names are decided after projection (docs/contract.md, "Viewer terms": FRONT faces the camera, LEFT is
image-left), so a mirror flip or a yaw past a side keeps every label's meaning.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from cuboidgen.config import SceneConfig
from shared.shapes import Shape

MIN_DEPTH = 0.05  # nearest corner's z as a fraction of the distance; closer draws are redrawn


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


def draw_view(shape: Shape, scene: SceneConfig, size: int, rng: np.random.Generator) -> View:
    """Draw one view of `shape` from `scene`'s ranges, framed into a size x size image."""
    while True:
        params = draw_params(shape, scene, rng)
        camera = to_camera(object_points(shape, params), params)
        if camera[:, 2].min() > MIN_DEPTH * params["distance"]:
            break
    image = camera[:, :2] / camera[:, 2:3]
    order, swaps = viewer_order(shape, camera, image)
    params.update(swaps)
    camera, image = camera.take(order, axis=0), image.take(order, axis=0)  # faster than camera[order]
    keypoints, framing = frame(image, size, scene, rng)
    params.update(framing)
    return View(keypoints=keypoints, points3d=camera, ratios=shape.ratios(camera), params=params)


_EXTENTS = ("width", "height", "depth")
_POSE = ("pitch_deg", "yaw_deg", "roll_deg", "offset_x", "offset_y", "distance", "camera_pitch_deg")


def draw_params(shape: Shape, scene: SceneConfig, rng: np.random.Generator) -> dict:
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


# Per Table 1 corner: whether it takes the LEFT x, the BOTTOM y and the FRONT z.
_CORNER_SIDES = tuple(((c >> 1) & 1, c & 1, (c >> 2) & 1) for c in range(8))


def box_corners(x_right: float, x_left: float, y_top: float, y_bottom: float, depth: float) -> list[tuple]:
    """The 8 corners of an axis-aligned box in Table 1 order (4*front + 2*left + bottom),
    as (x, y, z) tuples: numpy costs more than it saves on 24 numbers."""
    return [
        (x_left if left else x_right, y_bottom if bottom else y_top, -depth / 2 if front else depth / 2)
        for left, bottom, front in _CORNER_SIDES
    ]


def object_points(shape: Shape, p: dict) -> np.ndarray:
    """Keypoints in the object frame; all parts share the ground (y = height / 2)."""
    w, h, d = p["width"], p["height"], p["depth"]
    if len(shape.parts) == 1:
        return np.array(box_corners(w / 2, -w / 2, -h / 2, h / 2, d))
    middle = w / 2 - p["split"] * w  # the shared wall, split * width from the right side
    low = h * p["height_ratio"]
    h_left, h_right = (h, low) if p["left_taller"] else (low, h)
    points = [None] * shape.num_keypoints
    for part, corners in zip(shape.parts, (
        box_corners(w / 2, middle, h / 2 - h_right, h / 2, d),
        box_corners(middle, -w / 2, h / 2 - h_left, h / 2, d),
    )):
        for index, corner in zip(part, corners):
            points[index] = corner
    return np.array(points)


def rotation(pitch_deg: float, yaw_deg: float, roll_deg: float) -> list[list[float]]:
    """Yaw about the vertical, then pitch about x, then roll about the optical axis:
    Rz(roll) Rx(pitch) Ry(yaw), multiplied out by hand (rows, plain floats: numpy's
    per-call cost is most of the work on nine numbers)."""
    a, b, c = math.radians(pitch_deg), math.radians(yaw_deg), math.radians(roll_deg)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    # Rx Ry has rows (cb, 0, sb), (sa sb, ca, -sa cb), (-ca sb, sa, ca cb); Rz mixes the first two.
    r1, r2, r3 = (cb, 0.0, sb), (sa * sb, ca, -sa * cb), (-ca * sb, sa, ca * cb)
    return [
        [cc * r1[0] - sc * r2[0], -sc * r2[1], cc * r1[2] - sc * r2[2]],
        [sc * r1[0] + cc * r2[0], cc * r2[1], sc * r1[2] + cc * r2[2]],
        list(r3),
    ]


def camera_tilt(pitch_up_deg: float) -> tuple[float, float]:
    """(cos, sin) of a camera tilted up, which maps level-frame (y, z) to
    (cos y + sin z, -sin y + cos z): things ahead move down."""
    t = math.radians(pitch_up_deg)
    return math.cos(t), math.sin(t)


def to_camera(points: np.ndarray, p: dict) -> np.ndarray:
    ct, st = camera_tilt(p["camera_pitch_deg"])
    r1, r2, r3 = rotation(p["pitch_deg"], p["yaw_deg"], p["roll_deg"])
    y, z = p["offset_y"], p["distance"]
    # The tilt mixes the rotation's last two rows, and the offset's y and z, alike.
    linear = [r1, [ct * u + st * v for u, v in zip(r2, r3)], [ct * v - st * u for u, v in zip(r2, r3)]]
    offset = [p["offset_x"], ct * y + st * z, ct * z - st * y]
    if p["flip"]:
        linear[0] = [-u for u in linear[0]]  # a mirror image; viewer_order renames the corners
        offset[0] = -offset[0]
    transform = np.array([*zip(*linear), offset])  # (4, 3): linear transposed, then the offset
    return points @ transform[:3] + transform[3]


def viewer_order(shape: Shape, camera: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, dict]:
    """The index order that names keypoints in viewer terms, and which swaps it made.

    LEFT must be image-left of RIGHT, FRONT nearer the camera than BACK.
    """
    left, right, front, back, mirror_lr, mirror_fb = _naming_tables(shape)
    xs, zs = image[:, 0].tolist(), camera[:, 2].tolist()
    order = list(range(shape.num_keypoints))
    # Mirrored sets have equal sizes, so comparing sums compares means.
    swap_lr = sum(xs[i] for i in left) > sum(xs[i] for i in right)
    if swap_lr:
        order = [order[i] for i in mirror_lr]
    swap_fb = sum(zs[order[i]] for i in front) > sum(zs[order[i]] for i in back)
    if swap_fb:
        order = [order[i] for i in mirror_fb]
    return np.array(order), {"swap_left_right": swap_lr, "swap_front_back": swap_fb}


@functools.cache
def _naming_tables(shape: Shape) -> tuple[list[int], ...]:
    """LEFT, RIGHT, FRONT and BACK keypoints and the two mirror permutations, as lists."""
    sides = [shape.having(w).tolist() for w in ("LEFT", "RIGHT", "FRONT", "BACK")]
    return (*sides, shape.mirror_left_right.tolist(), shape.mirror_front_back.tolist())


def frame(image: np.ndarray, size: int, scene: SceneConfig, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Scale and shift projected points so the silhouette's longer side spans the image
    less two margins, centred with a small random shift (kept inside the image)."""
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
    keypoints = image * scale + origin
    return keypoints, {"margin": margin, "frame_scale": scale, "frame_origin": origin}
