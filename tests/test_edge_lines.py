"""cuboidtrain.geometry.edge_lines: a box's corners from its silhouette's straight edges, exact on exact
masks, robust to an occluder's notch, and what the fit takes from them (`fit.cuboid.outline_start`)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cuboidtrain.fit.cuboid import FROM_HEAT_MAPS, FROM_OUTLINE, FitStart, outline_start
from cuboidtrain.geometry.camera_params import project, rotation_vector
from cuboidtrain.geometry.edge_lines import corners_from_edges, cracks, edge_lines, outline_polygon, windowed
from cuboidtrain.geometry.mask_fit import fit_mask
from cuboidtrain.geometry.outline import MaskTarget
from shared.camera import rotation
from shared.raster import rasterize
from shared.shapes import get_shape

BOX = get_shape("box")
SIZE = 256


def box_view(rng: np.random.Generator, pitch_deg: float | None = None, yaw_deg: float | None = None,
             roll_deg: float | None = None) -> np.ndarray:
    """(8, 2) corners of a random box seen from above at a slant (three faces: a hexagon), in a
    SIZE px frame, perspective strength k = 0.3-0.5, rolled 4-12 degrees: an edge along a pixel
    row or column crosses a binary mask's rows in one step or none, and a line through it is
    known only to the step's half pixel over its length (up to 0.7 px at a vertex, unrolled)."""
    pitch = rng.uniform(20, 35) if pitch_deg is None else pitch_deg
    yaw = rng.uniform(25, 65) * rng.choice([-1, 1]) if yaw_deg is None else yaw_deg
    roll = rng.uniform(4, 12) * rng.choice([-1, 1]) if roll_deg is None else roll_deg
    vector = np.array([np.log(rng.uniform(0.7, 1.5)), np.log(rng.uniform(0.7, 1.5)),
                       *rotation_vector(np.array(rotation(-pitch, yaw, roll))), 0.0, 0.0,
                       np.log(60.0), rng.uniform(0.3, 0.5), SIZE / 2 + rng.uniform(-5, 5), SIZE / 2 + rng.uniform(-5, 5)])
    return project(vector, BOX, False)


def views(count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [box_view(rng) for _ in range(count)]


def fixed_by_outline(corners: np.ndarray, mask: np.ndarray):
    return corners_from_edges(edge_lines(mask, corners, outline_polygon(corners)), BOX)


def conditioning(truth: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V,) each outline edge's angle from the nearest pixel row or column (degrees), and (V,) the
    sine of the angle at each vertex (between edges i - 1 and i)."""
    polygon = truth[labels]
    step = np.roll(polygon, -1, axis=0) - polygon
    angle = np.degrees(np.arctan2(step[:, 1], step[:, 0])) % 90
    unit = step / np.linalg.norm(step, axis=1, keepdims=True)
    before = np.roll(unit, 1, axis=0)
    return np.minimum(angle, 90 - angle), np.abs(before[:, 0] * unit[:, 1] - before[:, 1] * unit[:, 0])


def test_the_exact_silhouette_s_edge_lines_give_the_true_corners():
    """Property over 40 random boxes: the exact silhouette's edge lines put every outline vertex
    within 0.5 px of the truth and each interior corner within 1 px, where the binary mask can
    tell: vertices whose edges run 4 degrees or more off the pixel grid (a line along a row is known
    to half a pixel) and cross at 37 degrees or more (a shallow crossing slides along the lines);
    interior corners where every edge is 3 degrees off the grid and crosses at 24 degrees or more."""
    vertices = interiors = 0
    for truth in views(40):
        labels = outline_polygon(truth)
        fixed = fixed_by_outline(truth, rasterize(BOX, truth, SIZE))
        assert fixed.on_outline.sum() == 6 and fixed.interior_fixed  # a hexagon: three faces seen
        off_grid, sine = conditioning(truth, labels)
        error = np.linalg.norm(fixed.keypoints - truth, axis=1)
        told = (off_grid >= 4) & (np.roll(off_grid, 1) >= 4) & (sine >= 0.6)
        assert (error[labels][told] < 0.5).all()
        vertices += told.sum()
        if (off_grid >= 3).all() and sine.min() >= 0.4:
            assert (error[~fixed.on_outline] < 1.0).all()
            interiors += 1
    assert vertices >= 100 and interiors >= 5  # the property was tested on enough cases


def test_the_edges_are_found_from_a_polygon_a_few_px_off():
    """The networks' corners, not the truth, split the outline: 3 px of noise on them moves nothing."""
    rng = np.random.default_rng(1)
    for truth in views(10, seed=1):
        labels = outline_polygon(truth)
        mask = rasterize(BOX, truth, SIZE)
        off = corners_from_edges(edge_lines(mask, truth + rng.normal(0, 3.0, truth.shape), labels), BOX)
        off_grid, sine = conditioning(truth, labels)
        told = (off_grid >= 4) & (np.roll(off_grid, 1) >= 4) & (sine >= 0.6)
        assert (np.linalg.norm(off.keypoints - truth, axis=1)[labels][told] < 0.5).all()


def line_gap(line, other, ends: np.ndarray) -> float:
    """The largest distance between two lines over an edge's two ends (px)."""
    return max(abs(other.normal @ end - other.offset - (line.normal @ end - line.offset)) for end in ends)


@pytest.mark.parametrize("seed", range(4))
def test_an_occluder_s_notch_moves_no_edge_line_by_more_than_a_pixel(seed):
    """Property over random boxes: a rectangle cut 5-15 px deep into the middle of any edge 40 px
    long or more, over a fifth to a third of it (what an occluder does), leaves every fitted edge
    line within 1 px of the uncut mask's."""
    rng = np.random.default_rng(100 + seed)
    for truth in views(5, seed=100 + seed):
        mask = rasterize(BOX, truth, SIZE)
        labels = outline_polygon(truth)
        clean = edge_lines(mask, truth, labels)
        polygon = truth[labels]
        long = np.flatnonzero(np.linalg.norm(np.roll(polygon, -1, axis=0) - polygon, axis=1) >= 40)
        edge = rng.choice(long)
        a, b = truth[labels[edge]], truth[labels[(edge + 1) % len(labels)]]
        inward = -clean.lines[edge].normal
        along = (b - a) / np.linalg.norm(b - a)
        middle = a + (b - a) * rng.uniform(0.4, 0.6)
        half, depth = np.linalg.norm(b - a) * rng.uniform(0.1, 0.17), rng.uniform(5, 15)
        notch = np.array([middle - half * along - 3 * inward, middle + half * along - 3 * inward,
                          middle + half * along + depth * inward, middle - half * along + depth * inward])
        cut = mask.copy()
        cv2.fillConvexPoly(cut.view(np.uint8), np.round(notch).astype(np.int32), 0)
        assert cut.sum() < mask.sum() - 20  # the notch took pixels
        notched = edge_lines(cut, truth, labels)
        for v in range(len(labels)):
            ends = truth[[labels[v], labels[(v + 1) % len(labels)]]]
            assert line_gap(clean.lines[v], notched.lines[v], ends) < 1.0


def test_the_necker_alternative_is_reported():
    truth = views(1, seed=3)[0]
    fixed = fixed_by_outline(truth, rasterize(BOX, truth, SIZE))
    interior = np.flatnonzero(~fixed.on_outline)
    assert len(interior) == 2 and fixed.necker is not None
    # the other box: the same outline, the front interior point taken by the back corner and back again
    np.testing.assert_allclose(fixed.necker[interior], fixed.keypoints[interior[::-1]])
    assert np.isnan(fixed.necker[fixed.on_outline]).all()


def test_a_face_seen_edge_on_leaves_the_interior_to_the_heat_maps():
    """Seen level with its top face and square-on, a box's outline is a quadrilateral: no vanishing
    point of its depth, no interior corner from the outline."""
    truth = box_view(np.random.default_rng(4), pitch_deg=0.0, yaw_deg=0.0, roll_deg=5.0)
    fixed = fixed_by_outline(truth, rasterize(BOX, truth, SIZE))
    assert not fixed.interior_fixed and fixed.necker is None
    assert np.isinf(fixed.sd_px[~fixed.on_outline]).all()


def noisy(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The mask with 3% of its outline pixels flipped at random: pixel-sized bumps, its edge lines
    still sharp (rms under `ROUGH_OUTLINE_PX`)."""
    edge = cv2.morphologyEx(mask.view(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    return np.where(edge & (rng.random(mask.shape) < 0.03), ~mask, mask)


@pytest.mark.parametrize("seed", [5, 6, 7, 8])
def test_the_fit_on_a_noisy_mask_follows_the_geometric_interior(seed):
    """Networks' interior corners 12 px off at full confidence, outline ones 2 px off, on a noisy
    mask: the start moves the interior onto the outline's geometry (within 3 px of the truth), the
    record says so, and the fit started from and pulled toward it ends within 1.1 px of the true
    interior, no farther than the fit from the networks' corners, which their pull drags (up to
    2.2 px on these boxes)."""
    rng = np.random.default_rng(seed)
    truth = views(1, seed=seed)[0]
    mask = noisy(rasterize(BOX, truth, SIZE), rng)
    on_outline = np.zeros(8, dtype=bool)
    on_outline[outline_polygon(truth)] = True
    offsets = rng.normal(0, 1, truth.shape)
    offsets *= np.where(on_outline, 2.0, 12.0)[:, None] / np.linalg.norm(offsets, axis=1, keepdims=True)
    networks = FitStart(MaskTarget.of(mask), truth + offsets, np.ones(8), None)
    start = outline_start(networks, mask, BOX, model_scale=0.25)
    assert start.interior == FROM_OUTLINE
    interior = ~on_outline
    assert np.linalg.norm(start.corners - truth, axis=1)[interior].max() < 3.0
    np.testing.assert_array_equal(start.network_corners(), networks.corners)  # what the error bars read

    def interior_error(s: FitStart) -> float:
        fit = fit_mask(s.target, BOX, s.corners, s.peaks)
        image = project(fit.camera.vector, BOX, fit.camera.mirror)  # the start's corner order
        return float(np.linalg.norm(image - truth, axis=1)[interior].mean())

    geometric = interior_error(start)
    assert geometric < 1.1 and geometric <= interior_error(networks) + 0.05


def test_a_twobox_start_is_left_to_the_heat_maps():
    twobox = get_shape("twobox")
    corners = np.random.default_rng(6).uniform(50, 200, (twobox.num_keypoints, 2))
    mask = np.zeros((SIZE, SIZE), dtype=bool)
    start = FitStart(MaskTarget.of(mask | True), corners, np.ones(len(corners)), None)
    assert outline_start(start, mask, twobox, model_scale=0.25) is start
    assert start.interior == FROM_HEAT_MAPS



def test_the_cracks_of_a_window_picked_from_the_whole_masks_are_those_found_in_it():
    """`windowed` picks from a mask's cracks those `cracks(mask, window)` finds, in its order: windows
    inside the mask's frame, across its edges and of one pixel's width."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        height, width = rng.integers(3, 60, 2)
        mask = rng.random((height, width)) > rng.uniform(0.2, 0.8)
        left, right = np.sort(rng.integers(0, width + 1, 2))
        top, bottom = np.sort(rng.integers(0, height + 1, 2))
        if left == right or top == bottom:
            continue
        found, picked = cracks(mask, (left, top, right, bottom)), windowed(*cracks(mask), (left, top, right, bottom))
        np.testing.assert_array_equal(picked[0], found[0])
        np.testing.assert_array_equal(picked[1], found[1])
