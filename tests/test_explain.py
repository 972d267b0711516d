"""Explanation pictures: the Figure 4 panel, the photo overlay, and the geometry they draw."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cuboidtrain.explain import Explainer, front_arrow, to_photo
from cuboidtrain.infer import infer_paths
from shared.shapes import get_shape
from tests.test_infer import Recording, hexagon, rect_keypoints, rectangles, stub_model, write_png


def test_to_photo_maps_pixel_centres_between_resolutions():
    # Mask pixel j covers photo pixels 2j and 2j + 1 at twice the resolution: its centre is 2j + 0.5.
    points = np.array([[0.0, 0.0], [3.0, 5.0], [-0.5, -0.5]])
    assert np.allclose(to_photo(points, (10, 20), (20, 40)), [[0.5, 0.5], [6.5, 10.5], [-0.5, -0.5]])
    assert np.allclose(to_photo(points, (10, 20), (10, 20)), points)


def test_the_front_arrow_points_from_the_front_face_away_from_the_back():
    geometry = get_shape("box")
    points = np.zeros((8, 2))
    points[geometry.having("FRONT")] = [[40.0, 10.0], [40.0, 30.0], [38.0, 10.0], [38.0, 30.0]]
    points[geometry.having("BACK")] = [[20.0, 12.0], [20.0, 28.0], [18.0, 12.0], [18.0, 28.0]]
    start, end = front_arrow(geometry, points)
    assert np.allclose(start, [39.0, 20.0])
    assert end[0] > start[0] + 3 and abs(end[1] - start[1]) < 1e-9


def test_the_panel_and_the_overlay_are_written_per_input(tmp_path):
    mask_path = write_png(tmp_path / "building.png", rectangles((60, 90), (10, 10, 70, 50)))
    other = write_png(tmp_path / "other.png", hexagon())
    photo = np.full((120, 180, 3), 128, np.uint8)  # the same view at twice the mask's resolution
    cv2.imwrite(str(tmp_path / "photo.jpg"), photo)
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))
    explainer = Explainer(tmp_path / "explain", [tmp_path / "photo.jpg", None])
    records = infer_paths([mask_path, other], [model], explain=explainer)
    names = sorted(p.name for p in (tmp_path / "explain").iterdir())
    assert names == ["building-overlay.png", "building.png", "other.png"]
    assert sorted(explainer.written) == sorted((tmp_path / "explain").iterdir())

    panel = cv2.imread(str(tmp_path / "explain" / "building.png"))
    assert panel.shape[1] > 1200 and panel.shape[0] > 600  # big enough to read the heat-map tiles
    overlay = cv2.imread(str(tmp_path / "explain" / "building-overlay.png"))
    assert overlay.shape == photo.shape  # one picture pixel per photo pixel
    # The rectangle's corners, mapped onto the photo, are drawn over; a far corner is untouched.
    corners = to_photo(np.array(records[0]["keypoints"]), (60, 90), (120, 180))
    for x, y in np.round(corners).astype(int):
        patch = overlay[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3].astype(int)
        assert np.abs(patch - 128).max() > 60
    assert np.abs(overlay[108:, 165:].astype(int) - 128).max() < 12  # JPEG noise only


def test_components_get_their_own_panels(tmp_path):
    path = write_png(tmp_path / "two.png", rectangles((60, 90), (5, 5, 40, 30), (60, 35, 80, 52)))
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))
    infer_paths([path], [model], all_components=True, explain=Explainer(tmp_path / "out"))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["two-0.png", "two-1.png"]


def test_a_missing_photo_is_an_option_error_and_an_unreadable_one_a_warning(tmp_path):
    path = write_png(tmp_path / "building.png", hexagon())
    with pytest.raises(ValueError, match="--overlay .*nope.jpg: no such file"):
        Explainer(tmp_path / "out", [tmp_path / "nope.jpg"])
    (tmp_path / "photo.jpg").write_text("not a photo")
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))
    records = infer_paths([path], [model], explain=Explainer(tmp_path / "out", [tmp_path / "photo.jpg"]))
    assert records[0]["error"] is None and records[0]["keypoints"] is not None
    assert "no overlay: --overlay" in records[0]["warnings"][0] and "cannot read it as an image" in records[0]["warnings"][0]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["building.png"]


def test_inputs_of_the_same_name_in_other_folders_get_their_own_panels(tmp_path):
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    paths = [write_png(tmp_path / d / "x.png", hexagon()) for d in ("a", "b")]
    refiner = Recording()
    model = stub_model("box", refiner, lambda: rect_keypoints(refiner.last, 8))
    explainer = Explainer(tmp_path / "out")
    infer_paths(paths, [model], explain=explainer)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["x-input1.png", "x.png"]
    assert len(set(explainer.written)) == 2
