"""Explanation pictures: the Figure 4 panel, the photo overlay, and the geometry they draw."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.infer.explain import Explainer, input_tile, front_arrow, overlay_zoom, to_photo
from shared.shapes import get_shape
from tests.conftest import infer_paths
from tests.test_infer import (Recording, checkpoints, hexagon, random_models, rect_keypoints,  # noqa: F401 (fixtures)
                              rectangles, stub_model, write_png)


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
    # A 180 px wide photo is drawn at 3 picture pixels per photo pixel: 540 px, at least 512 on the long side.
    assert overlay.shape == (3 * 120, 3 * 180, 3)
    # The rectangle's corners, mapped onto the photo, are drawn over; a far corner is untouched.
    corners = to_photo(np.array(records[0]["keypoints"]), (60, 90), (360, 540))
    for x, y in np.round(corners).astype(int):
        patch = overlay[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3].astype(int)
        assert np.abs(patch - 128).max() > 60
    assert np.abs(overlay[324:, 495:].astype(int) - 128).max() < 12  # JPEG noise only


@pytest.mark.parametrize("height, width, zoom", [(49, 70, 8), (120, 180, 3), (300, 512, 1), (1080, 1920, 1)])
def test_small_photos_are_overlaid_at_least_512_px_on_the_long_side(height, width, zoom):
    assert overlay_zoom(height, width) == zoom
    assert max(height, width) * zoom >= 512 and (zoom == 1 or max(height, width) * (zoom - 1) < 512)


def tile_pixels(fig, ax, x: float, y: float) -> np.ndarray:
    """The RGB pixels around data point (x, y) of `ax`, as drawn."""
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(int)
    px, py = ax.transData.transform((x, y))
    row, col = image.shape[0] - int(py), int(px)
    return image[row - 3 : row + 4, col - 3 : col + 4].reshape(-1, 3)


def test_the_area_outside_the_input_is_hatched_grey_not_the_foregrounds_white():
    import matplotlib.pyplot as plt

    mask = rectangles((40, 60), (10, 10, 50, 30)).astype(np.float64)  # 1 = building, drawn white
    geometry = get_shape("box")
    keypoints = np.array([[-30.0, 12.0], [50, 10], [10, 30], [50, 30], [12, 12], [48, 12], [12, 28], [48, 28]])
    fig, ax = plt.subplots(figsize=(4, 3), dpi=100)
    input_tile(ax, mask, geometry, keypoints)  # a corner 30 px left of the input: the view reaches past it
    outside, building, background = (tile_pixels(fig, ax, *p) for p in ((-20, 35), (30, 20), (4, 36)))
    assert 70 < outside.mean() < 190 and outside.min() < outside.max()  # grey, hatched
    assert building.mean() > 240 and background.mean() < 20  # white building, black background
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["outside the input"]
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(4, 3), dpi=100)
    inside = np.vstack([[10.0, 10.0], keypoints[1:]])
    input_tile(ax, mask, geometry, inside)  # the view within the input: nothing to mark
    assert ax.get_legend() is None
    plt.close(fig)


def test_the_cli_counts_its_pictures_in_words(tmp_path, checkpoints):
    path = write_png(tmp_path / "building.png", rectangles((60, 90), (10, 10, 70, 50)))
    out = tmp_path / ("pictures_of_a_building_in_a_folder_whose_name_is_long" * 2)  # past 80 columns
    result = CliRunner().invoke(app, ["infer", path, "--checkpoint", str(checkpoints["box"]),
                                      "--explain", str(out), "--json", str(tmp_path / "out.json")])
    assert result.exit_code == 0, result.output
    assert f"1 picture in {out}\n" in result.output  # the path whole on its line, not wrapped at 80 columns


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


def test_the_readme_caption_quotes_the_line_infer_prints_for_its_picture(monkeypatch):
    """docs/explain_figure.py runs `infer examples/building.png` as the README's caption says; the
    caption carries the line it prints, so a change to the fit or the line that leaves the picture and
    its caption behind fails here (the picture once showed depth x/ 4.43 against the command's 1.60)."""
    import importlib.util
    import re

    root = Path(__file__).resolve().parent.parent
    spec = importlib.util.spec_from_file_location("explain_figure", root / "docs" / "explain_figure.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    monkeypatch.chdir(root)
    readme = (root / "README.md").read_text(encoding="utf-8")
    caption = readme.split("](docs/explain-building.png)", 1)[1].split("\n\n", 2)[1]
    quoted = re.findall(r"`([^`]*)`", caption)
    assert script.answer_line() in quoted, quoted


def test_a_long_title_wraps_inside_the_panel(random_models):
    # A twobox's answer line and a warning in full run past 16 inches at 11 pt: the title wraps, and
    # every line of it lies inside the figure (a long warning once ran off both edges).
    from dataclasses import replace

    import matplotlib.pyplot as plt

    from cuboidtrain.fit.fitter import Fitter
    from cuboidtrain.fit.options import FitOptions
    from cuboidtrain.infer.explain import caption, explanation_figure

    fit = Fitter(random_models, FitOptions(device="cpu", cuboid=True)).fit(rectangles((90, 150), (10, 20, 140, 70)))
    fit = replace(fit, warnings=("weak-heatmaps: " + "the Estimator's heat maps peak low; check the mask " * 8,))
    assert max(len(line) for line in caption(fit, 60).splitlines()) <= 60
    fig = explanation_figure(fit)
    fig.canvas.draw()
    title, frame = fig._suptitle.get_window_extent(), fig.bbox
    assert frame.x0 <= title.x0 and title.x1 <= frame.x1 and title.y1 <= frame.y1
    highest = max(ax.title.get_window_extent().y1 for ax in fig.axes if ax.get_title())
    assert title.y0 >= highest  # above every tile's title: the band grew with the lines
    plt.close(fig)
