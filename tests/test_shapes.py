"""Keypoint tables, parts, edges and ratios against docs/contract.md ("Keypoints") and the paper's Tables 1 and 2."""
import numpy as np
import pytest

from shared.shapes import BOX, TWOBOX, get_shape


def test_box_follows_table_1():
    assert BOX.keypoint_names == (
        "BACK-RIGHT-TOP", "BACK-RIGHT-BOTTOM", "BACK-LEFT-TOP", "BACK-LEFT-BOTTOM",
        "FRONT-RIGHT-TOP", "FRONT-RIGHT-BOTTOM", "FRONT-LEFT-TOP", "FRONT-LEFT-BOTTOM",
    )


def test_twobox_follows_table_2_and_design_parts():
    assert TWOBOX.num_keypoints == 14
    assert TWOBOX.keypoint_names[8] == "BACK-MIDDLE-TOP(L)" and TWOBOX.keypoint_names[13] == "FRONT-LEFT-BOTTOM"
    assert [sorted(p) for p in TWOBOX.parts] == [list(range(8)), sorted([8, 9, 10, 11, 12, 13, 3, 7])]


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
def test_each_part_lists_corners_in_table_1_meaning(shape):
    # Corner c of every part must carry the depth/width/height words of Table 1's corner c,
    # with MIDDLE standing for the side shared with the other part.
    for name, part in zip(shape.part_names, shape.parts):
        for corner, index in enumerate(part):
            words = shape.keypoint_names[index].replace("(R)", "").replace("(L)", "").split("-")
            expected = BOX.keypoint_names[corner].split("-")
            if name == "right":
                expected = [w.replace("LEFT", "MIDDLE") for w in expected]
            if name == "left":
                expected = [w.replace("RIGHT", "MIDDLE") for w in expected]
            assert words == expected, (name, corner, shape.keypoint_names[index])


def test_edges_box_is_a_cube_wireframe():
    assert len(BOX.edges) == 12
    degree = np.bincount(np.array(BOX.edges).ravel())
    assert (degree == 3).all()


def test_edges_twobox_share_the_bottom_middle_edge_once():
    assert len(TWOBOX.edges) == 23
    assert TWOBOX.edges.count((3, 7)) == 1


@pytest.mark.parametrize("shape", [BOX, TWOBOX])
def test_mirrors_are_involutions(shape):
    for perm in (shape.mirror_left_right, shape.mirror_front_back):
        assert (perm[perm] == np.arange(shape.num_keypoints)).all()


def test_mirrors_swap_the_named_sides():
    assert BOX.mirror_left_right.tolist() == [2, 3, 0, 1, 6, 7, 4, 5]
    assert BOX.mirror_front_back.tolist() == [4, 5, 6, 7, 0, 1, 2, 3]
    lr = TWOBOX.mirror_left_right
    # BACK-RIGHT-TOP(R) <-> BACK-LEFT-TOP(L); the middle wall keeps its bottom, swaps its tops.
    assert (lr[0], lr[2], lr[3], lr[7], lr[11], lr[13]) == (9, 8, 3, 7, 6, 5)
    assert TWOBOX.mirror_front_back[[0, 3, 8, 10]].tolist() == [4, 7, 11, 13]


def test_ratios_of_a_known_box_and_round_trip():
    points = np.array([[x, y, z] for z in (1.0, -1.0) for x in (1.5, -1.5) for y in (-0.5, 0.5)])
    # Table 1 order is 4*front + 2*left + bottom: width 3, height 1, depth 2.
    ratios = BOX.ratios(points)
    assert ratios == pytest.approx({"depth_height": 2.0, "width_height": 3.0})
    assert BOX.ratio_dict(BOX.ratio_vector(ratios)) == pytest.approx(ratios)


def test_twobox_ratio_record_is_nested_by_part():
    record = {"right": {"depth_height": 1.0, "width_height": 2.0}, "left": {"depth_height": 3.0, "width_height": 4.0}}
    assert TWOBOX.ratio_names == ("right.depth_height", "right.width_height", "left.depth_height", "left.width_height")
    assert TWOBOX.ratio_vector(record).tolist() == [1.0, 2.0, 3.0, 4.0]
    assert TWOBOX.ratio_dict([1, 2, 3, 4]) == record


def test_unknown_shape_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown shape 'pyramid'.*box.*twobox"):
        get_shape("pyramid")
