"""A fit that reaches the silhouette (issue 37, Must have 4), and the error budget's oracles (Must have 1)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cuboidgen.config import SCENES
from cuboidgen.synth import make_sample
from cuboidtrain.fit.fitter import Fitter, Oracle
from cuboidtrain.fit.masks import warp
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry import edge_lines, mask_fit
from cuboidtrain.fit import cuboid
from cuboidtrain.geometry.outline import MaskTarget
from cuboidtrain.geometry.camera_params import CameraParams, from_sample_params, rotation_matrices
from shared.shapes import get_shape
from tests.conftest import small_library

# Clean generated box masks (`paper-clean`, 256 px) whose fit with the shipped grey-input box model
# stopped short of their silhouette before the restart (IoU 0.990, 0.985, 0.983; after it 0.992,
# 0.994, 0.995): the samples of seeds 5, 12 and 37.
SHORT_BOXES = (5, 12, 37)
# Clean twobox masks whose fit with the shipped grey-input twobox model stopped short before the
# restart (IoU 0.988, 0.986, 0.972; after it 0.995, 0.991, 0.998): the samples of seeds 8, 37 and 63.
SHORT_TWOBOXES = (8, 37, 63)
# A clean twobox whose restarts on the first fit's objective (the networks' pull and the Tabulator's
# anchor in it) stay short, IoU 0.9889, and reach 0.9922 on the silhouette first: the sample of seed 61.
PULLED_SHORT_TWOBOX = 61
# A clean twobox that the restart's turns of 10 degrees each way leave short (IoU 0.9895) and those of 5,
# 10 and 20 take to 0.9922: the sample of seed 175.
TURNED_FURTHER_TWOBOX = 175
# A clean twobox that its restarts leave short (IoU 0.9889), and settling its fit on the silhouette takes
# to 0.9917: the sample of seed 115.
SETTLED_TWOBOX = 115
# The clean twobox of seed 369: without the restart its twobox fit stops short, and the box is chosen.
TWOBOX_CHOSEN_AS_BOX = 369
# Clean masks of each class with a narrow face or a notch, whose outline vertices the starts read (the
# samples the binary-input models first stopped short on; geometry alone: no network reads them).
OUTLINE_BOXES = (13363269863109141259, 14377397759793473315, 4119973520403393625)
OUTLINE_TWOBOXES = (7830848198647218049, 2157578057008441671, 11009211302426209105)


def generated(seed: int, shape: str = "box", scene: str = "paper-clean"):
    return make_sample(shape, SCENES[scene], 256, seed, small_library())


def first_start_alone(monkeypatch) -> None:
    """The fit as before the restarts: no restart (RESTART_IOU below any IoU), and a fit that did not stop
    short not settled either (no settling iterations)."""
    monkeypatch.setattr(mask_fit, "RESTART_IOU", -1.0)
    monkeypatch.setattr(mask_fit, "SETTLE_ITERATIONS", 0)


@pytest.fixture(scope="module")
def box_fitter() -> Fitter:
    return Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, shape="box"))


@pytest.fixture(scope="module")
def networks() -> Fitter:
    return Fitter.from_shipped(FitOptions(device="cpu", shape="box"))


@pytest.mark.parametrize("seed", SHORT_BOXES)
def test_a_clean_box_that_stopped_short_reaches_its_silhouette(box_fitter, seed, monkeypatch):
    mask = generated(seed).clean
    assert box_fitter.fit(mask).cuboid.fit.iou >= 0.99
    first_start_alone(monkeypatch)
    assert box_fitter.fit(mask).cuboid.fit.iou < 0.99


@pytest.fixture(scope="module")
def twobox_fitter() -> Fitter:
    return Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, shape="twobox"))


@pytest.mark.parametrize("seed", SHORT_TWOBOXES)
def test_a_clean_twobox_that_stopped_short_reaches_its_silhouette(twobox_fitter, seed, monkeypatch):
    mask = generated(seed, "twobox").clean
    assert twobox_fitter.fit(mask).cuboid.fit.iou >= 0.99
    first_start_alone(monkeypatch)
    assert twobox_fitter.fit(mask).cuboid.fit.iou < 0.99


def test_a_clean_twobox_whose_own_fit_stopped_short_is_not_called_a_box(monkeypatch):
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    mask = generated(TWOBOX_CHOSEN_AS_BOX, "twobox").clean
    fit = fitter.fit(mask)
    assert fit.shape == "twobox" and fit.cuboid.fit.iou >= 0.99
    first_start_alone(monkeypatch)
    assert fitter.fit(mask).shape == "box"


def test_a_restart_fits_no_class_from_its_first_start_twice(monkeypatch):
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    calls = []
    first_fits = cuboid.first_fits
    monkeypatch.setattr(cuboid, "first_fits",
                        lambda *args, **kwargs: calls.append(args[1].name) or first_fits(*args, **kwargs))
    restarts = []
    restarted = mask_fit.restarted
    monkeypatch.setattr(mask_fit, "restarted", lambda *args, **kwargs: restarts.append(1) or restarted(*args, **kwargs))
    fitter.fit(generated(SHORT_TWOBOXES[0], "twobox").clean)
    assert restarts and sorted(calls) == ["box", "twobox"]


@pytest.mark.parametrize("axis", [1, 0])
@pytest.mark.parametrize("degrees", [-15.0, 8.0, 90.0])
def test_a_turned_box_keeps_its_centre_extents_and_the_axis_it_turned_about(degrees, axis):
    camera = from_sample_params(get_shape("twobox"), generated(5, "twobox").params)
    turned = mask_fit.turned(camera, degrees, axis)

    def axes(c: CameraParams) -> np.ndarray:
        return rotation_matrices(c.vector[None, 2:5])[0]

    other = 1 - axis  # vertical for a tilt, across the width for a turn
    np.testing.assert_allclose(axes(turned)[:, axis], axes(camera)[:, axis], atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(axes(turned)[:, other] @ axes(camera)[:, other], -1, 1))),
                               abs(degrees), atol=1e-6)  # the others turned by as much
    np.testing.assert_array_equal(turned.vector[[0, 1, 5, 6, 7, 8, 9, 10, 11, 12]],
                                  camera.vector[[0, 1, 5, 6, 7, 8, 9, 10, 11, 12]])
    np.testing.assert_allclose(mask_fit.turned(turned, -degrees, axis).keypoints(), camera.keypoints(), atol=1e-9)


@pytest.mark.parametrize("seed", OUTLINE_TWOBOXES)
def test_the_convex_outline_vertices_of_a_clean_twobox_are_its_corners(seed):
    mask = generated(seed, "twobox").clean
    vertices = mask_fit.convex_vertices(mask)
    for hull in mask_fit.hull_vertices(mask):  # every vertex of the hull is one (both simplified within 1.5 px)
        assert np.linalg.norm(vertices - hull, axis=1).min() <= 3.0
    rows, columns = np.mgrid[:mask.shape[0], :mask.shape[1]]
    for x, y in vertices:  # the mask fills less than half of a disc about a convex vertex, more about the notch's
        disc = (columns - x) ** 2 + (rows - y) ** 2 <= 5.0**2
        assert mask[disc].mean() < 0.6, (x, y)


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_the_restart_keeps_the_fit_whose_silhouette_explains_the_mask_better(shape, monkeypatch):
    monkeypatch.setattr(mask_fit, "SETTLE_ITERATIONS", 0)  # the restart alone: a fit that reached is not settled
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, shape=shape))
    seeds = (*SHORT_BOXES, 0, 1, 2) if shape == "box" else (5, 6, 7, 8, 9)
    masks = [generated(seed, shape).clean for seed in seeds]
    restarted = [fitter.fit(mask).cuboid.fit for mask in masks]
    short = mask_fit.RESTART_IOU
    first_start_alone(monkeypatch)
    first = [fitter.fit(mask).cuboid.fit for mask in masks]
    assert any(once.iou < short for once in first)  # the property is tried where a restart ran
    for again, once in zip(restarted, first):
        assert again.iou >= once.iou  # the silhouette never explains the mask less
        if once.iou >= short or again.iou == once.iou:
            np.testing.assert_array_equal(again.keypoints, once.keypoints)  # not restarted, or the restart not kept


def test_a_clean_box_is_no_box_with_a_seam(monkeypatch):
    # the clean box of seed 12: without the restart its twobox outdoes its box as a box with a seam
    mask = generated(12).clean
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    fit = fitter.fit(mask)
    assert fit.shape == "box" and not any("a box with a seam" in w for w in fit.warnings)
    monkeypatch.setattr(Fitter, "reached", lambda self, *args: {})  # no class refitted when another outdoes it
    assert any("a box with a seam" in w for w in fitter.fit(mask).warnings)


def test_a_noisy_mask_is_never_restarted(box_fitter, monkeypatch):
    masks = [generated(seed, scene="paper").noisy for seed in range(4)]
    assert not any(mask_fit.polygonal(mask) for mask in masks)
    restarted = [box_fitter.fit(mask).keypoints for mask in masks]
    first_start_alone(monkeypatch)
    for mask, keypoints in zip(masks, restarted):
        np.testing.assert_array_equal(box_fitter.fit(mask).keypoints, keypoints)


def test_a_restart_on_the_silhouette_first_reaches_where_the_networks_pull_held_it_short(twobox_fitter, monkeypatch):
    mask = generated(PULLED_SHORT_TWOBOX, "twobox").clean
    assert twobox_fitter.fit(mask).cuboid.fit.iou >= 0.99
    monkeypatch.setattr(mask_fit, "RESTART_PULL", 1.0)  # the restart on the first fit's objective, as before
    monkeypatch.setattr(Fitter, "settled", staticmethod(lambda *args: None))  # the restarts alone
    monkeypatch.setattr(mask_fit, "POLISH_ITERATIONS", 0)
    assert twobox_fitter.fit(mask).cuboid.fit.iou < 0.99


@pytest.mark.parametrize("seed", [8, 9, 37])
def test_a_clean_masks_true_cuboid_holds_when_the_outlines_misses_weigh_alike_and_drifts_on_the_occluders_weights(
        twobox_fitter, seed):
    """A clean mask's true cuboid has IoU 1: on the settling objective (`clean_silhouette`) it stays; on the
    restart's, whose occlusion-tolerant weights make an outline point inside the silhouette half a miss,
    every edge moves outward."""
    sample = generated(seed, "twobox")
    model = twobox_fitter.models[0]
    candidate = twobox_fitter.fit_framed(model, *twobox_fitter.framed(model, sample.clean))
    first = twobox_fitter.first_cuboid(candidate, MaskTarget.of(sample.clean)).first
    dense = mask_fit.StackedTargets.of([mask_fit.densely(t) for t in first.targets])
    truth = from_sample_params(get_shape("twobox"), sample.params)
    held, drifted = (mask_fit.fit_from(replace(first, weights=weigh(first.weights), stacked=dense), 0, truth).iou
                     for weigh in (mask_fit.clean_silhouette, mask_fit.silhouette_first))
    assert held >= 0.995 and drifted < held - 0.002, (held, drifted)


def test_a_chosen_fit_still_short_of_a_clean_silhouette_settles_on_it_and_keeps_its_class(twobox_fitter, monkeypatch):
    mask = generated(SETTLED_TWOBOX, "twobox").clean
    settled = twobox_fitter.fit(mask)
    monkeypatch.setattr(Fitter, "settled", staticmethod(lambda *args: None))
    short = twobox_fitter.fit(mask)
    assert short.cuboid.fit.iou < 0.99 <= settled.cuboid.fit.iou and settled.shape == short.shape == "twobox"
    assert settled.cuboid.fit.spread is not None  # its error bars, as any chosen fit's


def test_a_clean_twobox_out_of_reach_of_ten_degree_turns_reaches_by_smaller_and_larger_ones(twobox_fitter,
                                                                                           monkeypatch):
    mask = generated(TURNED_FURTHER_TWOBOX, "twobox").clean
    monkeypatch.setattr(Fitter, "settled", staticmethod(lambda *args: None))  # the restarts alone
    assert twobox_fitter.fit(mask).cuboid.fit.iou >= 0.99
    monkeypatch.setattr(mask_fit, "RESTART_TURNS_DEG", (-10.0, 10.0))
    assert twobox_fitter.fit(mask).cuboid.fit.iou < 0.99


@pytest.mark.parametrize("seed", [PULLED_SHORT_TWOBOX, SHORT_TWOBOXES[0]])
def test_a_restarted_answers_error_bars_read_the_objective_of_a_fit_never_restarted(twobox_fitter, seed):
    mask = generated(seed, "twobox").clean
    model = twobox_fitter.models[0]
    candidate = twobox_fitter.fit_framed(model, *twobox_fitter.framed(model, mask))
    first = twobox_fitter.first_cuboid(candidate, MaskTarget.of(mask)).first
    answers, fits = mask_fit.reach_silhouette(first, clean=[True])
    moved, never = answers[0], first.answers[0]
    assert fits[0].iou > first.fits[0].iou and moved.solved is not never.solved  # a restart or the polish was kept
    assert moved.solved.residuals == never.solved.residuals  # the same rows: the first fits' outline and pulls
    residual, _ = mask_fit._objective(first.stacked, first.shape, first.corners, first.confidence, first.prior_ratios,
                                      first.weights, np.array([0]), np.array([moved.mirror]), first.cameras)
    at = moved.solved.params[moved.row][None]
    np.testing.assert_allclose(moved.cost, 0.5 * np.sum(residual(at, np.array([0])) ** 2), rtol=1e-12)


def test_the_necker_twin_draws_the_same_picture_under_weak_perspective():
    sample = generated(3)
    camera = from_sample_params(get_shape("box"), sample.params)
    vector = camera.vector.copy()
    vector[8] = 0.0  # weak perspective: depth leaves the picture
    weak = CameraParams(camera.shape, vector, camera.mirror)
    twin = mask_fit.necker_twin(weak)
    np.testing.assert_allclose(twin.keypoints(), weak.keypoints(), atol=1e-9)
    assert twin.mirror != weak.mirror and not np.allclose(twin.vector[2:5], weak.vector[2:5])


@pytest.mark.parametrize("seed", OUTLINE_BOXES)
def test_the_hull_vertices_of_a_clean_mask_are_its_corners(seed):
    sample = generated(seed)
    vertices = mask_fit.hull_vertices(sample.clean)
    nearest = np.linalg.norm(vertices[:, None] - sample.keypoints[None], axis=2).min(1)
    assert len(vertices) >= 4 and nearest.max() < 3.0, nearest  # a sharp corner's tip is lost to the pixels
    assert edge_lines.signed_area(vertices) > 0


def test_the_true_heat_maps_put_the_networks_corners_on_the_truth(networks):
    sample = generated(3, scene="paper")
    plain = networks.fit(sample.noisy)
    told = networks.fit(sample.noisy, oracle=Oracle(keypoints=sample.keypoints))

    def error(fit) -> float:
        return float(np.linalg.norm(fit.keypoints - sample.keypoints, axis=1).mean())

    assert error(told) < 2.0 and error(told) < error(plain)


def test_the_true_clean_mask_stands_for_the_refiners_output(networks):
    sample = generated(3, scene="paper")
    told = networks.fit(sample.noisy, oracle=Oracle(refined=sample.clean))
    candidate = told.explanation.candidate
    assert told.refine_steps == 0
    np.testing.assert_array_equal(candidate.refined > 0, warp(sample.clean, candidate.framing))


def test_true_corners_of_another_class_are_refused():
    sample = generated(3)
    fitter = Fitter.from_shipped(FitOptions(device="cpu", shape="twobox"))
    with pytest.raises(ValueError, match="expected the twobox model's 14 corners"):
        fitter.fit(sample.clean, oracle=Oracle(keypoints=sample.keypoints))


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_a_clean_fit_that_reached_its_silhouette_settles_on_it_nearer_the_truth(shape, monkeypatch):
    """`mask_fit.SETTLE_ITERATIONS`: a clean mask's chosen fit, short or not, settles on its silhouette, kept
    where its IoU rises; the corners come nearer the true ones (the first fit's networks' pull and occluders'
    asymmetry held them a pixel off: BENCHMARKS.md, "Targets")."""
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True, shape=shape))
    samples = [generated(seed, shape) for seed in range(12)]  # a few of ambiguous depth move either way
    settled = [fitter.fit(sample.clean).cuboid.fit for sample in samples]
    monkeypatch.setattr(mask_fit, "SETTLE_ITERATIONS", 0)
    first = [fitter.fit(sample.clean).cuboid.fit for sample in samples]
    assert all(calm.iou >= once.iou for calm, once in zip(settled, first))
    moved = [calm.iou > once.iou for calm, once in zip(settled, first)]
    assert sum(moved) >= 6
    for calm, once, on in zip(settled, first, moved):
        if not on:  # not kept: the same fit
            np.testing.assert_array_equal(calm.keypoints, once.keypoints)

    def errors(fits) -> list[float]:  # each mask's mean corner error, as bench_accuracy's median reads them
        return [float(np.linalg.norm(fit.keypoints - sample.keypoints, axis=1).mean()) for fit, sample in zip(fits, samples)]

    assert np.median(errors(settled)) < 0.8 * np.median(errors(first))
