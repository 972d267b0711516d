"""3D IoU of oriented boxes (Objectron's measure): its properties, and a Monte Carlo check."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cuboidtrain.geometry.camera_params import rotation_matrices
from cuboidtrain.geometry.iou3d import OrientedBox, intersection_volume, iou, union_iou

coordinate = st.floats(-2.0, 2.0, allow_nan=False)
extent = st.floats(0.2, 3.0, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)


@st.composite
def rotations(draw) -> np.ndarray:
    return rotation_matrices(np.array([[draw(angle), draw(angle), draw(angle)]]) / np.sqrt(3))[0]


@st.composite
def boxes(draw) -> OrientedBox:
    centre = np.array([draw(coordinate) for _ in range(3)])
    return OrientedBox(centre, draw(rotations()), np.array([draw(extent) for _ in range(3)]))


@settings(max_examples=60, deadline=None)
@given(boxes())
def test_a_box_against_itself_is_one(box):
    assert iou(box, box) == pytest.approx(1.0, abs=1e-7)


@settings(max_examples=60, deadline=None)
@given(boxes(), boxes())
def test_iou_is_symmetric_and_in_range(a, b):
    forward, backward = iou(a, b), iou(b, a)
    assert 0.0 <= forward <= 1.0
    assert forward == pytest.approx(backward, abs=1e-7)


@settings(max_examples=60, deadline=None)
@given(boxes(), st.sampled_from([0, 1, 2]))
def test_a_box_shifted_by_half_its_extent_along_its_own_axis_is_one_third(box, axis):
    shifted = OrientedBox(box.centre + box.axes[:, axis] * box.size[axis] / 2, box.axes, box.size)
    assert iou(box, shifted) == pytest.approx(1 / 3, abs=1e-7)


@settings(max_examples=60, deadline=None)
@given(boxes(), rotations(), st.lists(st.floats(0.1, 1.0), min_size=3, max_size=3), st.floats(0.2, 1.0))
def test_a_contained_box_scores_its_share_of_the_volume(big, rotation, shape, fill):
    # A box whose circumscribed sphere fits in the big one's inscribed sphere lies inside it, however turned.
    size = np.array(shape) / np.linalg.norm(shape) * big.size.min() * fill
    small = OrientedBox(big.centre, rotation, size)
    assert iou(small, big) == pytest.approx(small.volume / big.volume, rel=1e-6, abs=1e-9)
    assert intersection_volume(big, small) == pytest.approx(small.volume, rel=1e-6)


@settings(max_examples=60, deadline=None)
@given(boxes(), boxes(), rotations(), st.lists(coordinate, min_size=3, max_size=3))
def test_moving_both_boxes_alike_keeps_their_iou(a, b, rotation, translation):
    moved = iou(a.transformed(rotation, np.array(translation)), b.transformed(rotation, np.array(translation)))
    assert moved == pytest.approx(iou(a, b), abs=1e-7)


def test_iou_agrees_with_monte_carlo():
    rng = np.random.default_rng(0)
    for _ in range(5):
        a, b = (OrientedBox(rng.normal(size=3) * 0.4, rotation_matrices(rng.normal(size=(1, 3)))[0],
                            rng.uniform(0.5, 2.0, 3)) for _ in range(2))
        corners = np.concatenate([a.corners(), b.corners()])
        points = rng.uniform(corners.min(0), corners.max(0), (200_000, 3))
        inside = [(np.abs((points - box.centre) @ box.axes) <= box.size / 2).all(1) for box in (a, b)]
        expected = (inside[0] & inside[1]).sum() / (inside[0] | inside[1]).sum()
        assert iou(a, b) == pytest.approx(expected, abs=0.01)


def test_disjoint_boxes_and_two_halves_of_one():
    whole = OrientedBox(np.zeros(3), np.eye(3), np.array([2.0, 1.0, 1.0]))
    far = OrientedBox(np.array([5.0, 0.0, 0.0]), np.eye(3), np.ones(3))
    assert iou(whole, far) == 0.0
    halves = [OrientedBox(np.array([x, 0.0, 0.0]), np.eye(3), np.ones(3)) for x in (-0.5, 0.5)]
    assert union_iou(halves, [whole]) == pytest.approx(1.0, abs=1e-7)
    assert union_iou(halves[:1], [whole]) == pytest.approx(0.5, abs=1e-7)


def test_a_box_from_its_table1_corners_is_the_same_box():
    box = OrientedBox(np.array([0.3, -0.2, 4.0]), rotation_matrices(np.array([[0.3, -1.1, 0.4]]))[0],
                      np.array([2.0, 1.0, 0.5]))
    # Table 1 (shared.shapes): corner c = 4 * FRONT + 2 * LEFT + BOTTOM; RIGHT is +x, BOTTOM +y, BACK +z.
    signs = np.array([[0.5 - ((c >> 1) & 1), ((c & 1) - 0.5), 0.5 - ((c >> 2) & 1)] for c in range(8)])
    rebuilt = OrientedBox.from_corners(box.centre + (signs * box.size) @ box.axes.T)
    assert np.allclose(rebuilt.size, box.size) and np.allclose(rebuilt.axes, box.axes)
    assert iou(rebuilt, box) == pytest.approx(1.0, abs=1e-7)
