"""Scenes: known poses land on known pixels; flips and yaw keep labels in viewer terms;
the same seed gives the same sample bit for bit."""
import hashlib
import json
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest

from cuboidgen.config import PAPER, SCENES, STREET, load_scene, scene_from_dict
from cuboidgen.occluders import OccluderLibrary
from shared.camera import Cuboid
from shared.raster import rasterize
from cuboidgen.scene import frame
from cuboidgen.synth import make_sample
from shared.sample import encode, to_record
from shared.shapes import BOX, TWOBOX
from tests.conftest import build_sample, centred

FRONT_ON = dict(width=1.0, height=1.0, depth=1.0, pitch_deg=0.0, yaw_deg=0.0, roll_deg=0.0,
                offset_x=0.0, offset_y=0.0, distance=3.0, camera_pitch_deg=0.0, flip=False)


def project(shape, params, size, rng, scene=None):
    named = Cuboid.from_params(params).named_corners(shape)
    intrinsics, _ = frame(named.image, size, scene or centred(), rng)
    return named.keypoints(intrinsics)


def test_front_on_unit_cube_projects_to_known_pixels(rng):
    # Front face at z = 2.5 projects to +-0.2, back face (z = 3.5) to +-1/7. The front square
    # spans 0.4 -> 48 px (64 px less 2 x 12.5% margins), centred on pixel 31.5.
    k = project(BOX, FRONT_ON, 64, rng)
    assert k[4] == pytest.approx((55.5, 7.5))  # FRONT-RIGHT-TOP
    assert k[7] == pytest.approx((7.5, 55.5))  # FRONT-LEFT-BOTTOM
    assert k[0] == pytest.approx((31.5 + 120 / 7, 31.5 - 120 / 7))  # BACK-RIGHT-TOP
    mask = rasterize(BOX, k, 64)
    expected = np.zeros((64, 64), bool)
    expected[8:56, 8:56] = True  # pixel centres 8..55 lie inside [7.5, 55.5]
    assert (mask == expected).all()


def test_flip_mirrors_the_image_and_keeps_viewer_labels(rng):
    pose = dict(FRONT_ON, yaw_deg=12.0, offset_x=0.7, pitch_deg=4.0)
    plain = project(BOX, pose, 64, rng)
    flipped = project(BOX, dict(pose, flip=True), 64, rng)
    mirrored = plain[BOX.mirror_left_right].copy()
    mirrored[:, 0] = 63 - mirrored[:, 0]
    assert flipped == pytest.approx(mirrored)


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
@pytest.mark.parametrize("scene", [PAPER, STREET])
def test_labels_keep_viewer_meaning_over_many_draws(shape, scene):
    pairs_lr = [(i, int(j)) for i, j in enumerate(shape.mirror_left_right) if "LEFT" in shape.keypoint_names[i]]
    for seed in range(60):
        sample = build_sample(seed, shape.name, size=64, scene=scene)
        k = sample.keypoints
        # LEFT-named corners are image-left of the RIGHT corners they mirror;
        # TOP corners are above the BOTTOM corners below them.
        assert all(k[i, 0] < k[j, 0] for i, j in pairs_lr), (seed, sample.params)
        for part in shape.parts:
            assert all(k[part[c], 1] < k[part[c + 1], 1] for c in (0, 2, 4, 6)), seed
        assert sample.params["flip"] in (True, False)


def test_flips_happen_about_half_the_time():
    flips = [build_sample(seed, size=32).params["flip"] for seed in range(200)]
    assert 60 < sum(flips) < 140


def test_street_verticals_converge_upward():
    # Camera tilted up: the top edge of the front face is shorter in the image than the bottom one.
    scene = replace(STREET, camera_pitch_deg=(20.0, 20.0), yaw_deg=(0.0, 0.0), offset_x=(0.0, 0.0), roll_deg=(0.0, 0.0))
    k = build_sample(3, size=128, scene=scene).keypoints
    assert np.linalg.norm(k[4] - k[6]) < np.linalg.norm(k[5] - k[7]) * 0.98


@pytest.mark.parametrize("shape", ["box", "twobox", "mix"])
def test_same_seed_same_sample_bit_for_bit(shape, library):
    a = encode(build_sample(42, shape, library=library))
    b = encode(build_sample(42, shape, library=library))
    c = encode(build_sample(43, shape, library=library))
    assert a == b and a != c


def test_sample_records_what_it_was_drawn_from():
    sample = build_sample(5, "twobox", scene=STREET)
    p = sample.params
    assert p["scene"] == "street" and sample.seed == 5
    for key in ("width", "height", "depth", "yaw_deg", "distance", "camera_pitch_deg", "split", "height_ratio",
                "flip", "margin", "occluders", "occluded_fraction", "contour_noise"):
        assert key in p, key


def test_scene_files_override_a_preset(tmp_path):
    path = tmp_path / "wide.toml"
    path.write_text('base = "street"\nyaw_deg = [-5.0, 5.0]\n')
    scene = load_scene(str(path))
    assert scene.name == "wide" and scene.yaw_deg == (-5.0, 5.0) and scene.eye_height == STREET.eye_height


@pytest.mark.parametrize("bad, match", [
    ({"yaw": [0, 1]}, "unknown field"),
    ({"yaw_deg": [5, -5]}, "yaw_deg.*min <= max"),
    ({"flip_probability": 2}, "flip_probability"),
    ({"base": "moon"}, "base must be one of"),
])
def test_bad_scene_files_are_clear_errors(bad, match):
    with pytest.raises(ValueError, match=match):
        scene_from_dict(dict(bad))


def test_unknown_scene_name_is_a_clear_error():
    with pytest.raises(ValueError, match="expected a preset"):
        load_scene("mars")


GENERATOR_DIGESTS = Path(__file__).parent / "data" / "generator_digests.json"


@pytest.fixture(scope="module")
def builtin_library():
    """The daemon's default library (`GenConfig().occluders` is None), as the digests were recorded with."""
    return OccluderLibrary.load(None)


def test_same_seed_same_bytes_as_recorded(builtin_library):
    """Every recorded "shape/scene/size/seed" encodes to the bytes it did when recorded (before the
    camera moved to shared/camera.py): a refactor of the generator must not change a sample. The
    digests are of format 1's bytes (the record in one map, no checksum): formats 2 and 3 wrap the
    same fields in a payload with its checksum, and the samples themselves did not change."""
    recorded = json.loads(GENERATOR_DIGESTS.read_text())
    assert len(recorded) == 72  # box, twobox, mix x three scenes x 64, 256 px x four seeds
    changed = []
    for key, digest in recorded.items():
        shape, scene, size, seed = key.split("/")
        record = to_record(make_sample(shape, SCENES[scene], int(size), int(seed), builtin_library))
        data = msgpack.packb({**record, "version": 1}, use_bin_type=True)  # format 1's bytes
        if hashlib.sha256(data).hexdigest() != digest:
            changed.append(key)
    assert changed == []
