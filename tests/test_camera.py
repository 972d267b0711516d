"""The perspective cuboid (shared/camera.py): the pose multiplied out by hand is the matrix
product; the generator's own params, projected here, give its keypoints bit for bit; viewer
naming holds over wild poses; the mirror flip and the params round-trip."""
from dataclasses import replace

import numpy as np
import pytest

from cuboidgen.config import PAPER, STREET
from cuboidgen.scene import draw_view
from cuboidgen.synth import seeded
from shared.camera import Cuboid, Extents, Intrinsics, Pose, project, rotation
from shared.shapes import BOX, TWOBOX
from tests.conftest import build_sample


def random_cuboid(shape, rng, flip=None) -> Cuboid:
    """Any extents and any yaw (past every side), a box well in front of the camera."""
    twobox = dict(split=rng.uniform(0.2, 0.8), height_ratio=rng.uniform(0.3, 0.9), left_taller=bool(rng.random() < 0.5))
    extents = Extents(*rng.uniform(0.5, 2.0, size=3), **(twobox if len(shape.parts) == 2 else {}))
    pitch, yaw, roll, tilt = rng.uniform(-30, 30), rng.uniform(-180, 180), rng.uniform(-20, 20), rng.uniform(-20, 20)
    pose = Pose(pitch, yaw, roll, offset_x=rng.uniform(-1, 1), offset_y=rng.uniform(-1, 1), distance=rng.uniform(6, 12),
                camera_pitch_deg=tilt, flip=bool(rng.random() < 0.5) if flip is None else flip)
    return Cuboid(extents, pose)


def test_the_pose_multiplied_out_matches_the_matrix_product(rng):
    """camera.rotation and Pose.to_camera multiply the pose out by hand: they must equal
    tilt @ Rz(roll) @ Rx(pitch) @ Ry(yaw), with the mirror flip on x."""

    def rx(t):
        return np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])

    def ry(t):
        return np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])

    def rz(t):
        return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])

    points = rng.uniform(-1, 1, size=(8, 3))
    for _ in range(50):
        pitch, yaw, roll, tilt = rng.uniform(-40, 40, size=4)
        expected = rz(np.radians(roll)) @ rx(np.radians(pitch)) @ ry(np.radians(yaw))
        assert np.allclose(rotation(pitch, yaw, roll), expected, atol=1e-12)
        p = dict(pitch_deg=pitch, yaw_deg=yaw, roll_deg=roll, camera_pitch_deg=tilt, flip=bool(rng.random() < 0.5),
                 offset_x=rng.uniform(-2, 2), offset_y=rng.uniform(0, 2), distance=rng.uniform(2, 10))
        pose = Pose(**p)
        up = np.radians(tilt)
        camera_tilt = np.array([[1, 0, 0], [0, np.cos(up), np.sin(up)], [0, -np.sin(up), np.cos(up)]])
        linear = camera_tilt @ expected
        offset = camera_tilt @ np.array([p["offset_x"], p["offset_y"], p["distance"]])
        if p["flip"]:
            linear[0], offset[0] = -linear[0], -offset[0]
        assert np.allclose(pose.to_camera(points), points @ linear.T + offset, atol=1e-12)


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
@pytest.mark.parametrize("scene", [PAPER, STREET])
def test_the_generators_params_projected_give_its_keypoints_exactly(shape, scene):
    for seed in range(40):
        view = draw_view(shape, scene, 64, seeded(seed))
        cuboid, intrinsics = Cuboid.from_params(view.params), Intrinsics.from_params(view.params)
        named = cuboid.named_corners(shape)
        assert np.array_equal(cuboid.keypoints(shape, intrinsics), view.keypoints), seed  # the same floats
        assert np.array_equal(named.camera, view.points3d)
        assert np.array_equal(project(named.camera, intrinsics), view.keypoints)
        assert named.naming.params() == {k: view.params[k] for k in ("swap_left_right", "swap_front_back")}


@pytest.mark.parametrize("shape", ["box", "twobox", "mix"])
def test_a_samples_params_reproduce_its_keypoints(shape):
    """What the fit path will read: a sample's params alone give its keypoints."""
    for seed in range(10):
        sample = build_sample(seed, shape, size=64, scene=STREET)
        geometry = BOX if sample.shape == "box" else TWOBOX
        keypoints = Cuboid.from_params(sample.params).keypoints(geometry, Intrinsics.from_params(sample.params))
        assert np.array_equal(keypoints, sample.keypoints)


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
def test_naming_puts_left_image_left_of_right_and_front_nearer(shape, rng):
    left, right, front, back = (shape.having(w) for w in ("LEFT", "RIGHT", "FRONT", "BACK"))
    swaps = set()
    for _ in range(200):
        named = random_cuboid(shape, rng).named_corners(shape)
        assert named.image[left, 0].mean() < named.image[right, 0].mean()
        assert named.camera[front, 2].mean() < named.camera[back, 2].mean()
        assert sorted(named.naming.order.tolist()) == list(range(shape.num_keypoints))  # a renaming, nothing lost
        swaps.add((named.naming.swap_left_right, named.naming.swap_front_back))
    assert swaps == {(False, False), (False, True), (True, False), (True, True)}  # every case was exercised


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
def test_the_mirror_flip_round_trips(shape, rng):
    """A flipped pose draws the plain picture mirrored about the principal point's column,
    with LEFT and RIGHT renamed; mirroring that back gives the plain keypoints."""
    intrinsics = Intrinsics(focal=150.0, principal=(31.5, 30.0))
    for _ in range(50):
        plain = random_cuboid(shape, rng, flip=False)
        flipped = replace(plain, pose=replace(plain.pose, flip=True))
        a, b = plain.named_corners(shape), flipped.named_corners(shape)
        assert a.naming.swap_left_right != b.naming.swap_left_right
        k_plain, k_flipped = a.keypoints(intrinsics), b.keypoints(intrinsics)
        back = k_flipped[shape.mirror_left_right]
        back[:, 0] = 2 * intrinsics.principal[0] - back[:, 0]
        assert back == pytest.approx(k_plain, abs=1e-9)
        assert (shape.mirror_left_right[shape.mirror_left_right] == np.arange(shape.num_keypoints)).all()


@pytest.mark.parametrize("flip", [False, True])
def test_to_object_undoes_to_camera(flip, rng):
    cuboid = random_cuboid(TWOBOX, rng, flip=flip)
    points = cuboid.object_points(TWOBOX)
    assert cuboid.pose.to_object(cuboid.camera_points(TWOBOX)) == pytest.approx(points, abs=1e-12)


def test_params_round_trip():
    for shape, scene in ((BOX, PAPER), (TWOBOX, STREET)):
        params = draw_view(shape, scene, 64, seeded(3)).params
        cuboid, intrinsics = Cuboid.from_params(params), Intrinsics.from_params(params)
        assert cuboid.params() == {k: params[k] for k in cuboid.params()}
        assert ("split" in cuboid.params()) == (shape is TWOBOX)
        assert Cuboid.from_params(cuboid.params()) == cuboid
        assert intrinsics.params() == {"frame_scale": params["frame_scale"], "frame_origin": params["frame_origin"]}


def test_the_principal_point_is_where_the_optical_axis_lands():
    intrinsics = Intrinsics(focal=100.0, principal=(12.0, 20.0))
    points = np.array([[0.0, 0.0, 5.0], [1.0, -2.0, 4.0]])
    assert project(points, intrinsics).tolist() == [[12.0, 20.0], [37.0, -30.0]]


def test_extents_that_do_not_fit_the_shape_are_clear_errors():
    with pytest.raises(ValueError, match="box has no split"):
        Extents(1.0, 1.0, 1.0, split=0.5, height_ratio=0.5).object_points(BOX)
    with pytest.raises(ValueError, match="twobox needs split and height_ratio"):
        Extents(1.0, 1.0, 1.0).object_points(TWOBOX)
