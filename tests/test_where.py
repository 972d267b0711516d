"""Where the error is: hull against interior corners, NME and ratio errors."""
from __future__ import annotations

import numpy as np

from cuboidtrain.fit.where import corner_errors, hull_corners, summarise
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
