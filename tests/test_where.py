"""Where the error is: hull against interior corners, NME and ratio errors."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cuboidtrain.geometry.camera_params import describe, from_sample_params, rotation_matrices, rotation_vector
from cuboidtrain.geometry.accuracy import (Truth, against_truth, camera_boxes, corner_errors, focal_error, hull_corners,
                                      iou_up_to_scale, solid_yaw_deg, summarise, yaw_error_deg)
from shared.shapes import get_shape

RATIOS = {"depth_height": 0.5, "width_height": 2.0}


def test_a_box_seen_from_a_corner_hides_one_corner_inside_its_hexagon():
    shape = get_shape("box")
    # An isometric-like box: a hexagon of six corners, two corners inside it (front and back centre).
    hexagon = [(100 + 50 * np.cos(a), 100 + 50 * np.sin(a)) for a in np.arange(6) * np.pi / 3]
    truth = np.array(hexagon + [(100, 100), (101, 101)], dtype=np.float64)
    assert hull_corners(truth).tolist() == [True] * 6 + [False, False]
    moved = truth.copy()
    moved[6] += (3.0, 4.0)
    errors = corner_errors(shape, moved, truth, {"depth_height": 0.55, "width_height": 2.0}, RATIOS)
    assert errors.hull.max() == 0 and errors.interior.tolist() == [5.0, 0.0]
    assert np.isclose(errors.nme, 5.0 / 8 / 100)  # the span is the hexagon's 100 px width
    summary = summarise([errors])
    assert np.isclose(summary["depth_height_mean_rel"], 0.1) and summary["width_height_mean_rel"] == 0
    assert summary["interior_share"] == 0.25


# --- yaw and 3D IoU against the generator's camera -------------------------------------------------


def _views(shape: str, scene: str, count: int, seed: int = 0):
    from cuboidgen.config import SCENES
    from cuboidgen.scene import draw_view

    rng = np.random.default_rng(seed)
    return [draw_view(get_shape(shape), SCENES[scene], 256, rng) for _ in range(count)]


def _truth(view) -> Truth:
    shape = get_shape("twobox" if len(view.keypoints) == 14 else "box")
    return Truth(shape, view.keypoints, view.ratios, from_sample_params(shape, view.params))


def _turned(camera, degrees: float):
    """The same cuboid turned by `degrees` about its own vertical: R -> R Ry(degrees)."""
    turn = np.radians(degrees)
    rotation = rotation_matrices(camera.vector[None, 2:5])[0] @ np.array(
        [[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    vector = camera.vector.copy()
    vector[2:5] = rotation_vector(rotation)
    return replace(camera, vector=vector)


@pytest.mark.parametrize("scene", ["paper", "street"])
@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_the_truth_against_itself_has_no_yaw_error_and_a_3d_iou_of_one(shape, scene):
    for view in _views(shape, scene, 10):
        truth = _truth(view)
        errors = against_truth(view.keypoints, view.ratios, truth, truth.camera)
        assert errors.yaw_deg == 0.0 and errors.iou3d == pytest.approx(1.0, abs=1e-7) and errors.focal == 0.0
        assert errors.hull.max() == 0 and errors.interior.max() == 0


def test_the_truths_yaw_is_the_generators_for_a_level_unmirrored_view():
    # paper views keep the camera level; flips and swaps rename the corners (the yaw is then the solid's)
    checked = 0
    for view in _views("box", "paper", 40, seed=2):
        p = view.params
        if p["camera_pitch_deg"] == 0 and not (p["flip"] or p["swap_left_right"] or p["swap_front_back"]):
            assert solid_yaw_deg(_truth(view).camera) == pytest.approx(p["yaw_deg"], abs=1e-9)
            checked += 1
    assert checked >= 5


def test_yaw_error_is_the_turn_modulo_a_half_turn():
    truth = _truth(_views("box", "street", 1, seed=3)[0]).camera
    for turn, expected in ((7.0, 7.0), (-30.0, 30.0), (100.0, 80.0), (180.0, 0.0), (-179.0, 1.0)):
        assert yaw_error_deg(_turned(truth, turn), truth) == pytest.approx(expected, abs=1e-7)


def test_a_box_named_the_other_way_round_is_the_same_solid():
    truth = _truth(_views("box", "street", 1, seed=4)[0]).camera
    half_turn = _turned(truth, 180.0)  # its sides named the other way: the same box
    mirrored = replace(truth, mirror=not truth.mirror)  # a box is its own mirror image
    for other in (half_turn, mirrored):
        assert yaw_error_deg(other, truth) == pytest.approx(0.0, abs=1e-7)
        assert iou_up_to_scale(other, truth) == pytest.approx(1.0, abs=1e-7)
    # the record's yaw of a mirrored description is the reflected pose's: -yaw
    assert describe(mirrored, 0.0).yaw_deg == pytest.approx(-describe(truth, 0.0).yaw_deg, abs=1e-7)


def test_3d_iou_is_taken_at_the_truths_depth():
    truth = _truth(_views("box", "street", 1, seed=5)[0]).camera
    turned = _turned(truth, 90.0)  # a box turned a quarter about its centre: overlap of two crossed boxes
    boxes = camera_boxes(truth)
    (w, h, d) = boxes[0].size
    overlap = min(w, d) ** 2 * h
    assert iou_up_to_scale(turned, truth) == pytest.approx(overlap / (2 * w * h * d - overlap), abs=1e-7)
    weak = truth.vector.copy()
    weak[8] = 0.0  # an infinitely far camera: a point at the truth's depth
    assert iou_up_to_scale(replace(truth, vector=weak), truth) == 0.0
    assert np.isnan(focal_error(replace(truth, vector=weak), truth))
    farther = truth.vector.copy()
    farther[7] += np.log(2.0)  # twice the px per height unit at the same depth: twice the focal length
    assert focal_error(replace(truth, vector=farther), truth) == pytest.approx(1.0)


def test_the_networks_corners_are_lifted_for_their_3d_figures():
    view = _views("twobox", "street", 1, seed=6)[0]
    truth = _truth(view)
    exact = against_truth(view.keypoints, view.ratios, truth)  # no camera given: the corners are lifted
    assert exact.yaw_deg == pytest.approx(0.0, abs=1e-4) and exact.iou3d == pytest.approx(1.0, abs=1e-4)
    unposed = against_truth(view.keypoints, view.ratios, replace(truth, camera=None))
    summary = summarise([exact, unposed])
    assert summary["posed"] == 1 and summary["iou3d_mean"] == pytest.approx(1.0, abs=1e-4)
    assert np.isnan(summarise([unposed])["yaw_mean_deg"])


def test_a_camera_inside_the_box_is_counted():
    view = _views("box", "street", 1, seed=7)[0]
    truth = _truth(view)
    outside = against_truth(view.keypoints, view.ratios, truth, truth.camera)
    assert 0 < outside.nearest_depth < 1  # a real street view: every corner in front, the nearest nearer than the centre
    inside = truth.camera.vector.copy()
    inside[8] = 3.0 / np.exp(inside[:2]).max()  # the camera a third of the box's longer side from its centre
    moved = against_truth(view.keypoints, view.ratios, truth, replace(truth.camera, vector=inside))
    assert moved.nearest_depth <= 0
    summary = summarise([outside, moved])
    assert summary["camera_inside"] == 1 and summary["nearest_depth_min"] == pytest.approx(moved.nearest_depth)
    assert np.isnan(against_truth(view.keypoints, view.ratios, replace(truth, camera=None)).nearest_depth)
