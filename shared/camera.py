"""The perspective cuboid: a box (or two) with extents and a pose, seen by a pinhole camera,
its corners named in viewer terms.

The paper's recipe (3.3.1): a canonical box, a non-uniform scale, a rotation and a
translation, then a perspective projection. The generator draws these numbers
(cuboidgen/scene.py); fitting a box to a mask searches them. Both go through this module,
so a drawn sample and a fitted box mean the same thing by the same parameters. Frames:

* object: x toward the box's RIGHT, y down (BOTTOM), z away (BACK); centre at 0;
* camera: OpenCV's, x right, y down, z forward; the image plane is x/z, y/z;
* pixels: focal length times the image plane plus the principal point (`Intrinsics`),
  integer = pixel centre (docs/contract.md, "Coordinates").

Names are decided after projection (docs/contract.md, "Viewer terms": FRONT faces the
camera, LEFT is image-left), so a mirror flip or a yaw past a side keeps every label's meaning.

The generator runs this for every sample: on 8 or 14 corners and nine rotation numbers,
plain floats and lists cost less than numpy's per-call overhead, hence the hand-multiplied
matrices. Changing the order of any arithmetic here changes the generator's samples
(tests/test_scene.py compares them with recorded digests).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from shared.shapes import Shape

# The params keys (docs/contract.md, "Sample format": params) each part is read from.
EXTENT_KEYS = ("width", "height", "depth")
TWOBOX_KEYS = ("split", "height_ratio", "left_taller")
POSE_KEYS = ("pitch_deg", "yaw_deg", "roll_deg", "offset_x", "offset_y", "distance", "camera_pitch_deg", "flip")


@dataclass(frozen=True)
class Extents:
    """The box's size in scene units; a twobox also has the three numbers of its split."""

    width: float  # x
    height: float  # y: the taller part's height
    depth: float  # z
    split: float | None = None  # twobox: the shared wall sits split * width from the RIGHT side
    height_ratio: float | None = None  # twobox: the lower part's height / the taller part's
    left_taller: bool = False  # twobox: whether the part on the object's -x side (shape.parts[1]) is the taller

    def object_points(self, shape: Shape) -> np.ndarray:
        """(N, 3) keypoints in the object frame, in `shape`'s order; all parts share the
        ground (y = height / 2)."""
        w, h, d = self.width, self.height, self.depth
        if len(shape.parts) == 1:
            if self.split is not None:
                raise ValueError(f"a {shape.name} has no split (got split={self.split}); only twobox has one")
            return np.array(box_corners(w / 2, -w / 2, -h / 2, h / 2, d))
        if self.split is None or self.height_ratio is None:
            raise ValueError(f"a {shape.name} needs split and height_ratio, got {self.split}, {self.height_ratio}")
        middle = w / 2 - self.split * w  # the shared wall, split * width from the right side
        low = h * self.height_ratio
        h_left, h_right = (h, low) if self.left_taller else (low, h)
        points = [None] * shape.num_keypoints
        for part, corners in zip(shape.parts, (
            box_corners(w / 2, middle, h / 2 - h_right, h / 2, d),
            box_corners(middle, -w / 2, h / 2 - h_left, h / 2, d),
        )):
            for index, corner in zip(part, corners):
                points[index] = corner
        return np.array(points)


@dataclass(frozen=True)
class Pose:
    """Where the box stands relative to the camera: a rotation, a translation, the camera's
    tilt and an optional mirror image."""

    pitch_deg: float  # about the object's x, after the yaw
    yaw_deg: float  # about the vertical
    roll_deg: float  # about the optical axis, last
    offset_x: float  # the centre's x in the level (untilted) camera frame
    offset_y: float  # its y (down); the ground is offset_y + height / 2
    distance: float  # its z
    camera_pitch_deg: float = 0.0  # the camera tilted up by this much: verticals converge upward
    flip: bool = False  # mirror the image left-right (viewer naming renames the corners)

    def transform(self) -> tuple[list[list[float]], list[float]]:
        """(linear, offset): camera = linear @ object + offset, as rows of plain floats."""
        ct, st = camera_tilt(self.camera_pitch_deg)
        r1, r2, r3 = rotation(self.pitch_deg, self.yaw_deg, self.roll_deg)
        y, z = self.offset_y, self.distance
        # The tilt mixes the rotation's last two rows, and the offset's y and z, alike.
        linear = [r1, [ct * u + st * v for u, v in zip(r2, r3)], [ct * v - st * u for u, v in zip(r2, r3)]]
        offset = [self.offset_x, ct * y + st * z, ct * z - st * y]
        if self.flip:
            linear[0] = [-u for u in linear[0]]  # a mirror image; viewer_order renames the corners
            offset[0] = -offset[0]
        return linear, offset

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) object-frame points -> the camera frame."""
        linear, offset = self.transform()
        transform = np.array([*zip(*linear), offset])  # (4, 3): linear transposed, then the offset
        return points @ transform[:3] + transform[3]

    def to_object(self, points: np.ndarray) -> np.ndarray:
        """The inverse of `to_camera`: the linear part is orthogonal (a rotation, perhaps
        mirrored), so its inverse is its transpose."""
        linear, offset = self.transform()
        return (points - np.array(offset)) @ np.array(linear)


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


# Per Table 1 corner: whether it takes the LEFT x, the BOTTOM y and the FRONT z.
_CORNER_SIDES = tuple(((c >> 1) & 1, c & 1, (c >> 2) & 1) for c in range(8))


def box_corners(x_right: float, x_left: float, y_top: float, y_bottom: float, depth: float) -> list[tuple]:
    """The 8 corners of an axis-aligned box in Table 1 order (4*front + 2*left + bottom),
    as (x, y, z) tuples: numpy costs more than it saves on 24 numbers."""
    return [
        (x_left if left else x_right, y_bottom if bottom else y_top, -depth / 2 if front else depth / 2)
        for left, bottom, front in _CORNER_SIDES
    ]


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera without skew or distortion, square pixels: pixel = focal * (x/z, y/z)
    + principal. The generator's framing (`frame_scale`, `frame_origin`) is exactly this."""

    focal: float  # px per unit of the image plane (x/z)
    principal: tuple[float, float]  # px: where the optical axis meets the image

    @classmethod
    def from_params(cls, params: dict) -> Intrinsics:
        """The camera a generated sample was framed with (its params' frame_scale, frame_origin)."""
        x, y = params["frame_origin"]
        return cls(focal=params["frame_scale"], principal=(x, y))

    def params(self) -> dict:
        """The sample params' names for this camera; the inverse of `from_params`."""
        return {"frame_scale": self.focal, "frame_origin": list(self.principal)}

    def to_pixels(self, image: np.ndarray) -> np.ndarray:
        """(N, 2) image-plane points (x/z, y/z) -> pixels."""
        return image * self.focal + self.principal


def perspective(points: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) image-plane points x/z, y/z."""
    return points[:, :2] / points[:, 2:3]


def project(points: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) pixels."""
    return intrinsics.to_pixels(perspective(points))


@dataclass(frozen=True)
class Cuboid:
    """A shape's geometry in the camera's frame: its extents and its pose."""

    extents: Extents
    pose: Pose

    @classmethod
    def from_params(cls, params: dict) -> Cuboid:
        """The cuboid a generated sample's params describe (other keys are ignored)."""
        # Spelled out, not looped over the key tuples: the generator builds one per sample,
        # and this is about half the cost (1 us, not 2).
        p = params
        if "split" in p:
            extents = Extents(p["width"], p["height"], p["depth"], p["split"], p["height_ratio"], p["left_taller"])
        else:
            extents = Extents(p["width"], p["height"], p["depth"])
        pose = Pose(p["pitch_deg"], p["yaw_deg"], p["roll_deg"], p["offset_x"], p["offset_y"], p["distance"],
                    p["camera_pitch_deg"], p["flip"])
        return cls(extents, pose)

    def params(self) -> dict:
        """The sample params' names for this cuboid; the inverse of `from_params`."""
        e = self.extents
        twobox = (e.split, e.height_ratio, e.left_taller) if e.split is not None else ()
        return {
            **{k: getattr(e, k) for k in EXTENT_KEYS},
            **dict(zip(TWOBOX_KEYS, twobox)),
            **{k: getattr(self.pose, k) for k in POSE_KEYS},
        }

    def object_points(self, shape: Shape) -> np.ndarray:
        """(N, 3) keypoints in the object frame, in `shape`'s (unnamed) order."""
        return self.extents.object_points(shape)

    def camera_points(self, shape: Shape) -> np.ndarray:
        """(N, 3) keypoints in the camera frame, in `shape`'s (unnamed) order."""
        return self.pose.to_camera(self.extents.object_points(shape))

    def named_corners(self, shape: Shape) -> NamedCorners:
        """The keypoints projected and named in viewer terms."""
        return name_corners(shape, self.camera_points(shape))

    def keypoints(self, shape: Shape, intrinsics: Intrinsics) -> np.ndarray:
        """(N, 2) pixels, named in viewer terms: what a sample's keypoints are."""
        return self.named_corners(shape).keypoints(intrinsics)


@dataclass(frozen=True)
class Naming:
    """How the keypoints are renamed in viewer terms: `order[i]` is the unnamed index that
    takes name i, after swapping LEFT/RIGHT and then FRONT/BACK as flagged."""

    order: np.ndarray  # (N,) int
    swap_left_right: bool
    swap_front_back: bool

    def params(self) -> dict:
        """The sample params' names for the swaps."""
        return {"swap_left_right": self.swap_left_right, "swap_front_back": self.swap_front_back}


@dataclass(frozen=True)
class NamedCorners:
    """A shape's keypoints in viewer order: in the camera frame and on the image plane."""

    camera: np.ndarray  # (N, 3) camera frame
    image: np.ndarray  # (N, 2) image plane, x/z and y/z
    naming: Naming

    def keypoints(self, intrinsics: Intrinsics) -> np.ndarray:
        """(N, 2) pixels under `intrinsics`."""
        return intrinsics.to_pixels(self.image)


def name_corners(shape: Shape, camera: np.ndarray) -> NamedCorners:
    """Project camera-frame keypoints (in `shape`'s order) and name them in viewer terms."""
    image = perspective(camera)
    naming = viewer_order(shape, camera, image)
    # take: faster than camera[order] on a few rows
    return NamedCorners(camera.take(naming.order, axis=0), image.take(naming.order, axis=0), naming)


def viewer_order(shape: Shape, camera: np.ndarray, image: np.ndarray) -> Naming:
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
    return Naming(np.array(order), swap_lr, swap_fb)


@functools.cache
def _naming_tables(shape: Shape) -> tuple[list[int], ...]:
    """LEFT, RIGHT, FRONT and BACK keypoints and the two mirror permutations, as lists."""
    sides = [shape.having(w).tolist() for w in ("LEFT", "RIGHT", "FRONT", "BACK")]
    return (*sides, shape.mirror_left_right.tolist(), shape.mirror_front_back.tolist())
