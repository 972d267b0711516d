"""Keypoint extractors and the Point Distribution Model, on heat maps with known peaks."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cuboidgen.config import PAPER
from cuboidgen.scene import draw_view
from cuboidtrain.experiments.generated_pdm import generated_pdm
from cuboidtrain.fit.extractors import argmax, centre_of_mass, dark, make_extractor
from cuboidtrain.fit.heatmaps import render_heatmaps
from cuboidtrain.fit.options import EXTRACTORS, parse_components
from cuboidtrain.fit.pdm import MIN_SAMPLES, PointDistributionModel
from shared.shapes import get_shape
from tests.conftest import tiny_model, with_generated_pdm

SIZE = 64


def random_peaks(seed: int, count: int = 16, border: float = 6.0) -> torch.Tensor:
    """(2, count/2, 2) sub-pixel keypoints at least `border` px inside a SIZE image."""
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(2, count // 2, 2, generator=generator, dtype=torch.float64) * (SIZE - 1 - 2 * border) + border


def distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.vector_norm(a.double() - b.double(), dim=-1)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
@pytest.mark.parametrize("seed", range(3))
def test_decoders_find_sub_pixel_gaussian_peaks(seed, sigma):
    truth = random_peaks(seed)
    maps = render_heatmaps(truth, SIZE, sigma)
    assert distances(dark(maps, sigma=sigma), truth).max() < 0.01  # a Gaussian's log is a quadratic: exact
    assert distances(centre_of_mass(maps), truth).max() < 0.2
    grid = distances(argmax(maps), truth)
    assert grid.max() <= 2**0.5 / 2 + 1e-6 and (argmax(maps) == argmax(maps).round()).all()


def test_decoders_follow_a_peak_moved_by_a_tenth_of_a_pixel():
    base = torch.tensor([[[30.0, 20.0]]], dtype=torch.float64)
    moved = base + torch.tensor([0.1, -0.1], dtype=torch.float64)
    a, b = (render_heatmaps(p, SIZE, 1.0) for p in (base, moved))
    assert torch.allclose(dark(b) - dark(a), torch.tensor([0.1, -0.1]).float(), atol=2e-3)
    assert torch.equal(argmax(a), argmax(b))  # whole pixels only


def test_the_brighter_of_two_blobs_wins_and_dark_stays_on_it():
    truth = torch.tensor([[[12.3, 40.6]]], dtype=torch.float64)
    decoy = torch.tensor([[[50.0, 10.0]]], dtype=torch.float64)
    maps = render_heatmaps(truth, SIZE, 1.0) + 0.3 * render_heatmaps(decoy, SIZE, 1.0)
    assert distances(argmax(maps), truth).max() < 0.71
    assert distances(dark(maps), truth).max() < 0.05
    assert distances(centre_of_mass(maps), truth).max() < 0.2  # the decoy is below half the maximum


def test_peaks_at_the_border_and_flat_maps_give_finite_points_inside_the_image():
    edge = torch.tensor([[[0.0, 0.0], [63.0, 31.2], [0.4, 63.0]]], dtype=torch.float64)
    maps = torch.cat([render_heatmaps(edge, SIZE, 1.0), torch.zeros(1, 1, SIZE, SIZE)], dim=1)
    for decode in (argmax, centre_of_mass, dark):
        points = decode(maps)
        assert torch.isfinite(points).all() and (points >= -0.5).all() and (points <= SIZE - 0.5).all()
    assert distances(dark(maps)[:, :3], edge).max() < 0.75  # the replicated border clips the Newton step


def test_tabulator_extractor_passes_t_through_and_names_are_checked():
    model = with_generated_pdm(tiny_model("box", 32))
    tabulated = torch.rand(1, 8, 2)
    assert make_extractor("tabulator", model)(torch.rand(1, 8, 32, 32), tabulated) is tabulated
    with pytest.raises(ValueError, match="--extractor 'soft'.*tabulator, argmax, centre-of-mass, dark, pdm"):
        make_extractor("soft", model)
    for name in EXTRACTORS:
        points = make_extractor(name, model)(render_heatmaps(tabulated * 31, 32, 1.0), tabulated)
        assert points.shape == (1, 8, 2)


# --- the Point Distribution Model ------------------------------------------------------------

def generated_sets(shape: str, count: int, seed: int) -> np.ndarray:
    rng, geometry = np.random.default_rng(seed), get_shape(shape)
    return np.stack([draw_view(geometry, PAPER, SIZE, rng).keypoints for _ in range(count)])


@pytest.fixture(scope="module")
def pdm():
    return generated_pdm("box", SIZE, 2000, seed=0)


def test_all_components_reproduce_any_valid_shape_and_fewer_approximate_it(pdm):
    held_out = generated_sets("box", 100, seed=99)
    full = np.linalg.norm(pdm.project(held_out, len(pdm.variances)) - held_out, axis=-1).max(axis=1)
    # Exact, except a rare shape beyond the training shapes' range, which is clipped onto it.
    assert (full < 1e-9).mean() >= 0.95 and full.max() < 0.5
    errors = [np.linalg.norm(pdm.project(held_out, k) - held_out, axis=-1).mean() for k in (2, 4, 6, 9)]
    assert errors == sorted(errors, reverse=True) and errors[-1] < 0.5
    assert np.linalg.norm(pdm.project(held_out, 0.999) - held_out, axis=-1).mean() < 0.5


def test_projection_keeps_position_and_scale(pdm):
    shapes = generated_sets("box", 10, seed=5)
    moved = shapes * 1.7 + np.array([11.0, -4.0])
    assert np.allclose(pdm.project(moved, 9), pdm.project(shapes, 9) * 1.7 + np.array([11.0, -4.0]), atol=1e-9)


def test_a_misplaced_corner_is_pulled_back_towards_a_valid_shape(pdm):
    truth = generated_sets("box", 50, seed=7)
    broken = truth.copy()
    broken[:, 3] += np.array([6.0, -5.0])  # one corner 7.8 px off, as a wrong argmax would put it
    fixed = pdm.project(broken, 6)
    before = np.linalg.norm(broken[:, 3] - truth[:, 3], axis=-1).mean()
    after = np.linalg.norm(fixed[:, 3] - truth[:, 3], axis=-1).mean()
    assert after < 0.6 * before


def test_active_components_from_a_count_or_a_variance_fraction(pdm):
    counts = [pdm.active_components(f) for f in (0.5, 0.9, 0.99, 0.999)]
    assert counts == sorted(counts) and counts[0] >= 1 and counts[-1] <= 16
    explained = np.cumsum(pdm.variances) / pdm.variances.sum()
    assert explained[counts[1] - 1] >= 0.9 and (counts[1] == 1 or explained[counts[1] - 2] < 0.9)
    assert pdm.active_components(4) == 4
    with pytest.raises(ValueError, match="PDM components 17: expected 1 to 16"):
        pdm.active_components(17)


@pytest.mark.parametrize("text, value", [("6", 6), ("0.98", 0.98), (0.5, 0.5), (3, 3)])
def test_parse_components(text, value):
    assert parse_components(text) == value and type(parse_components(text)) is type(value)


@pytest.mark.parametrize("text", ["0", "1.5", "-2", "all", "1.0"])
def test_parse_components_rejects_other_values(text):
    with pytest.raises(ValueError, match=f"PDM components {text!r}: expected a count"):
        parse_components(text)


def test_a_pdm_needs_enough_well_formed_sets():
    with pytest.raises(ValueError, match=f"999 keypoint sets: a PDM needs at least {MIN_SAMPLES}"):
        PointDistributionModel.fit(np.zeros((999, 8, 2)))
    with pytest.raises(ValueError, match=r"shape \(1000, 8\): expected \(M, N, 2\)"):
        PointDistributionModel.fit(np.zeros((1000, 8)))


def test_twobox_pdm_and_extractor_on_true_maps():
    model = with_generated_pdm(tiny_model("twobox", SIZE))
    truth = torch.from_numpy(generated_sets("twobox", 4, seed=3))
    points = make_extractor("pdm", model, pdm_components="0.999")(render_heatmaps(truth, SIZE, 1.0), None)
    assert points.shape == truth.shape and distances(points, truth).mean() < 0.6


def test_the_cli_offers_every_extractor_and_the_library_default():
    from cuboidtrain import cli
    from cuboidtrain.fit import options

    assert [choice.value for choice in cli.ExtractorChoice] == list(options.EXTRACTORS)
    assert [choice.value for choice in cli.FitShape] == list(options.FIT_SHAPES)
    assert float(typer_default(cli.infer, "pdm_components")) == options.DEFAULT_PDM_COMPONENTS
    assert typer_default(cli.infer, "margin") == options.DEFAULT_MARGIN


def test_a_model_without_a_pdm_says_how_to_get_one():
    with pytest.raises(ValueError, match="carries no point distribution model.*--pdm-spool"):
        make_extractor("pdm", tiny_model("box", 32))


def test_a_pdm_survives_its_trip_through_a_model_file(pdm):
    again = PointDistributionModel.from_dict(pdm.to_dict())
    shapes = generated_sets("box", 5, seed=9)
    assert np.array_equal(again.project(shapes, 6), pdm.project(shapes, 6))


def typer_default(command, name: str):
    import inspect

    return inspect.signature(command).parameters[name].default.default


def test_dark_uses_the_mixed_derivative_on_a_tilted_blob():
    # A correlated Gaussian: a sign slip in the Hessian's off-diagonal term would show.
    ys, xs = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64), torch.arange(SIZE, dtype=torch.float64), indexing="ij")
    dx, dy = xs - 30.4, ys - 20.7
    blob = torch.exp(-(0.5 * dx**2 + 0.7 * dx * dy + 0.5 * dy**2) / 2)[None, None].float()
    assert distances(dark(blob, sigma=0.5), torch.tensor([[[30.4, 20.7]]])).max() < 0.05


def test_flat_maps_give_the_image_centre_or_the_argmax():
    maps = torch.full((1, 2, 8, 8), 0.3)
    maps[0, 1] = 0.0  # no mass at all
    assert torch.allclose(centre_of_mass(maps), torch.tensor([[[3.5, 3.5], [0.0, 0.0]]]))  # argmax: first pixel
