"""The panel's 3D tiles (cuboidtrain/infer/box_view.py): the box framed, at one scale, from a side
that shows every face, its numbers apart, every mark in a legend; the camera from above."""
from __future__ import annotations

import itertools
import math

import cv2
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.colors import to_hex  # noqa: E402

from cuboidgen.config import PAPER_CLEAN  # noqa: E402
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.infer.box_view import BoxFrame, face_cosines, projected, view_angles  # noqa: E402
from cuboidtrain.infer.explain import explanation_figure  # noqa: E402
from cuboidtrain.infer.mesh import camera_box  # noqa: E402
from shared.shapes import get_shape  # noqa: E402
from tests.conftest import build_sample  # noqa: E402

# a clean box and twobox at 256 px, and a 64 px twobox: the panels the README and a small crop get
MASKS = {"box": ("box", 1, 256), "twobox": ("twobox", 1, 256), "small": ("twobox", 4, 64)}


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    """Each mask's panel, drawn, with its fit (the shipped models, as infer fits)."""
    folder = tmp_path_factory.mktemp("box-view")
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    drawn = {}
    for name, (shape, seed, size) in MASKS.items():
        path = str(folder / f"{name}.png")
        assert cv2.imwrite(path, build_sample(seed, shape, size=size, scene=PAPER_CLEAN).clean.astype(np.uint8) * 255)
        fit = fitter.fit(path)
        figure = explanation_figure(fit)
        figure.canvas.draw()
        drawn[name] = (fit, figure)
    yield drawn
    for _, figure in drawn.values():
        plt.close(figure)


def tiles(figure):
    """(the 3D tile, the plan tile): the 3D axes, and the axes titled 'from above'."""
    box = next(ax for ax in figure.axes if ax.name == "3d")
    plan = next(ax for ax in figure.axes if ax.get_title().startswith("from above"))
    return box, plan


@pytest.mark.parametrize("name", MASKS)
def test_the_box_fills_its_tile_at_one_scale(figures, name):
    fit, figure = figures[name]
    ax, _ = tiles(figure)
    frame = BoxFrame.of(camera_box(fit.cuboid.fit))
    at = projected(ax, frame.corners)
    spans = np.ptp(at, axis=0) / [ax.bbox.width, ax.bbox.height]
    assert spans.max() >= 0.75 and spans.min() >= 0.3, spans  # was about a tenth of a two-column tile
    limits = np.array([np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()), np.ptp(ax.get_zlim())])
    aspect = ax.get_box_aspect()
    assert np.allclose(aspect / aspect.max(), limits / limits.max())  # equal scale on every axis
    # drawn as fitted: the box's own extents are the record's ratios (units: its height)
    part = list(frame.shape.parts[0])
    extent = np.ptp(frame.corners[part], axis=0)
    ratios = frame.shape.ratio_vector(fit.ratios)
    assert np.allclose([extent[1] / extent[2], extent[0] / extent[2]], ratios[:2], rtol=1e-6)


@pytest.mark.parametrize("name", MASKS)
def test_no_face_is_seen_edge_on(figures, name):
    """Each face's drawn area over its area face-on (px per unit measured on the drawing) is at least
    0.3: a face seen edge-on (four corners on a line) would be near 0."""
    fit, figure = figures[name]
    ax, _ = tiles(figure)
    frame = BoxFrame.of(camera_box(fit.cuboid.fit))
    azimuth = math.radians(ax.azim)
    across = np.array([[0.0, 0.0, 0.0], [-math.sin(azimuth), math.cos(azimuth), 0.0]])  # a unit across the view
    scale = np.linalg.norm(np.diff(projected(ax, across), axis=0))
    part = list(frame.shape.parts[0])
    for face in ([0, 1, 5, 4], [0, 1, 3, 2], [0, 2, 6, 4]):  # RIGHT, BACK, TOP: one face of each normal
        quad = frame.corners[[part[i] for i in face]]
        true = np.linalg.norm(np.cross(quad[1] - quad[0], quad[3] - quad[0]))
        drawn = projected(ax, quad)
        x, y = drawn.T
        area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
        assert area / (true * scale**2) >= 0.3, (face, area / (true * scale**2))


@pytest.mark.parametrize("name", MASKS)
def test_the_box_is_drawn_upright_turned_not_mirrored(figures, name):
    fit, _ = figures[name]
    box = camera_box(fit.cuboid.fit)
    frame = BoxFrame.of(box)
    geometry = frame.shape
    assert frame.corners[geometry.having("TOP"), 2].min() > frame.corners[geometry.having("BOTTOM"), 2].max()
    assert np.allclose(frame.corners[geometry.having("BOTTOM"), 2], 0.0, atol=1e-9)  # standing on the ground
    part = list(geometry.parts[0])

    def handedness(points):
        return np.linalg.det(points[[part[1], part[2], part[4]]] - points[part[0]])

    assert np.sign(handedness(frame.corners)) == np.sign(handedness(box.corners))  # a rotation: never a mirror
    distances = [np.linalg.norm(c[:, None] - c[None], axis=-1) for c in (frame.corners, box.corners)]
    assert np.allclose(*distances, atol=1e-9)
    # the camera where it was: as far from every corner as in the camera's frame (at its origin)
    assert np.allclose(np.linalg.norm(frame.corners - frame.camera, axis=1), np.linalg.norm(box.corners, axis=1))


def test_the_view_is_30_to_60_degrees_off_every_side_face_on_the_cameras_side():
    """The property, over cameras all round a box: the view turns towards the camera by at most 15
    degrees from a diagonal, is 20-35 degrees above, and shows the camera's side."""
    box = get_shape("box")
    # corner i in its own axes: bit 4 FRONT (y -0.3), bit 2 LEFT (x -0.5), bit 1 BOTTOM (z 0), as Table 1
    corners = np.array([[-0.5 if i & 2 else 0.5, -0.3 if i & 4 else 0.3, 0.0 if i & 1 else 1.0] for i in range(8)])
    for bearing, height in itertools.product(range(-180, 180, 7), (-3.0, 0.5, 4.0, 40.0)):
        camera = np.array([8 * math.cos(math.radians(bearing)), 8 * math.sin(math.radians(bearing)), height])
        frame = BoxFrame(box, corners, camera)
        elevation, azimuth = view_angles(frame)
        off = azimuth % 90.0
        assert 30.0 <= off <= 60.0 and 20.0 <= elevation <= 35.0
        assert face_cosines(elevation, azimuth).min() >= 0.3
        assert math.cos(math.radians(azimuth - bearing)) > 0.5  # within 60 degrees of the camera's bearing


@pytest.mark.parametrize("name", MASKS)
def test_labels_titles_and_legends_do_not_overlap(figures, name):
    """The 3D tile's corner numbers apart from each other; every tile's title, axis labels and legend,
    and the figure's title and legends, apart from each other (the twobox panel's 3D axis labels ran
    into the heat maps' titles)."""
    fit, figure = figures[name]
    renderer = figure.canvas.get_renderer()
    ax, _ = tiles(figure)
    numbers = [t.get_window_extent(renderer) for t in ax.texts]
    assert len(numbers) == len(fit.keypoints)
    for a, b in itertools.combinations(numbers, 2):
        assert not a.overlaps(b)
    boxes = [figure._suptitle.get_window_extent(renderer)]
    boxes += [legend.get_window_extent(renderer) for legend in figure.legends]
    for tile in figure.axes:
        texts = [tile.title] + ([] if tile.name == "3d" else [tile.xaxis.label, tile.yaxis.label])
        boxes += [t.get_window_extent(renderer) for t in texts if t.get_text() and t.get_visible()]
        if tile.get_legend() is not None:
            boxes.append(tile.get_legend().get_window_extent(renderer))
    for a, b in itertools.combinations(boxes, 2):
        assert not a.overlaps(b), (a, b)


@pytest.mark.parametrize("name", ["box", "small"])
def test_every_mark_of_the_3d_tiles_and_the_front_arrow_has_a_legend_entry(figures, name):
    fit, figure = figures[name]
    for ax in tiles(figure):
        legend = ax.get_legend()
        colours = {to_hex(h.get_color()) for h in legend.legend_handles if hasattr(h, "get_color")}
        colours |= {to_hex(h.get_facecolor()) for h in legend.legend_handles if hasattr(h, "get_facecolor")}
        drawn = {to_hex(line.get_color()) for line in ax.lines}
        drawn |= {to_hex(c) for collection in ax.collections for c in collection.get_facecolor()}
        drawn |= {to_hex(p.get_facecolor()) for p in ax.patches}
        assert drawn <= colours, drawn - colours
    arrow = next(a for a in figure.axes if a.get_title().startswith("refined"))
    arrows = {to_hex(t.arrow_patch.get_edgecolor()) for t in arrow.texts if getattr(t, "arrow_patch", None)}
    shared = {to_hex(h.get_color()) for legend in figure.legends for h in legend.legend_handles}
    labels = [t.get_text() for legend in figure.legends for t in legend.get_texts()]
    assert arrows and arrows <= shared and any("front-facing" in label for label in labels)


def test_the_3d_tile_writes_both_ratios_with_their_sd(figures):
    fit, figure = figures["box"]
    ax, plan = tiles(figure)
    sd = fit.cuboid.ratios_sd()
    assert ax.get_title().split("\n")[1] == (f"d/h {fit.ratios['depth_height']:.2f} ± {sd['depth_height']:.2f}, "
                                            f"w/h {fit.ratios['width_height']:.2f} ± {sd['width_height']:.2f}")
    assert "focal length fitted, centre fitted" in plan.get_title()


def test_labels_of_corners_that_nearly_coincide_are_placed_apart():
    """A box seen nearly head-on puts corners 4 and 0, 5 and 1 within a few pixels of each other: their
    numbers' badges (8 x 11 px here) still do not overlap, and each stays within 3 gaps of its corner."""
    from cuboidtrain.infer.box_view import label_centres, overlap

    at = np.array([[100.0, 100], [100, 20], [20, 100], [20, 20], [103, 102], [102, 18], [24, 97], [21, 23]])
    halves = np.full((8, 2), [4.0, 5.5])
    centres = label_centres(at, halves, gap=12.0)
    boxes = [(c - h, c + h) for c, h in zip(centres, halves)]
    assert not any(overlap(a, b) for a, b in itertools.combinations(boxes, 2))
    assert (np.linalg.norm(centres - at, axis=1) <= 3 * 12.0).all()
