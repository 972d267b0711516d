"""The keypoint codec (heat maps from keypoints, keypoints read back by every extractor) and the
Point Distribution Model, on heat maps with known peaks."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cuboidgen.config import PAPER
from cuboidgen.scene import draw_view
from cuboidtrain.experiments.generated_pdm import generated_pdm
from cuboidtrain.models.codec import (CODECS, Decoded, argmax, centre_of_mass, dark, default_sigma, make_codec,
                                   render_heatmaps)
from cuboidtrain.models.settings import EXTRACTORS, parse_components
from cuboidtrain.models.pdm import MIN_SAMPLES, PointDistributionModel
from shared.shapes import get_shape
from tests.conftest import tiny_model, with_generated_pdm

SIZE = 64
MAP_SIZE = 32  # px, the encoding tests'


def random_keypoints(count: int, margin: float, seed: int = 0) -> torch.Tensor:
    """(1, count, 2) sub-pixel keypoints at least `margin` px inside a MAP_SIZE px image."""
    g = torch.Generator().manual_seed(seed)
    return margin + torch.rand(1, count, 2, generator=g, dtype=torch.float64) * (MAP_SIZE - 1 - 2 * margin)


# ---- encoding: render_heatmaps on the pixel-centre convention -------------------------------


def test_peak_is_exactly_one_at_an_integer_keypoint_row_y_column_x():
    keypoints = torch.tensor([[[5.0, 20.0], [20.0, 5.0], [0.0, 31.0]]])  # (x, y)
    maps = render_heatmaps(keypoints, MAP_SIZE, sigma=1.5)
    assert maps.shape == (1, 3, MAP_SIZE, MAP_SIZE) and maps.dtype == torch.float32
    for n, (x, y) in enumerate(keypoints[0].long().tolist()):
        assert maps[0, n, y, x] == 1.0  # row y, column x
        assert maps[0, n].max() == 1.0
        assert (maps[0, n] == 1.0).sum() == 1
        assert divmod(int(maps[0, n].argmax()), MAP_SIZE) == (y, x)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_centre_of_mass_of_a_sub_pixel_map_is_the_keypoint(sigma):
    # integers are pixel centres: the map's centre of mass over pixel centres j, i
    # must be the keypoint itself, not the keypoint +- 0.5
    keypoints = random_keypoints(20, margin=4 * sigma, seed=int(sigma * 10))
    maps = render_heatmaps(keypoints, MAP_SIZE, sigma).double()[0]  # (20, H, W)
    grid = torch.arange(MAP_SIZE, dtype=torch.float64)
    mass = maps.sum(dim=(1, 2))
    com_x = (maps * grid[None, None, :]).sum(dim=(1, 2)) / mass
    com_y = (maps * grid[None, :, None]).sum(dim=(1, 2)) / mass
    err = torch.stack([com_x, com_y], dim=1) - keypoints[0]
    assert err.abs().max() < 0.01, err.abs().max()


def test_argmax_pixel_is_the_rounded_keypoint():
    keypoints = random_keypoints(20, margin=3.0, seed=7)
    maps = render_heatmaps(keypoints, MAP_SIZE, sigma=1.0)[0]
    for n, (x, y) in enumerate(keypoints[0].tolist()):
        assert divmod(int(maps[n].argmax()), MAP_SIZE) == (round(y), round(x))


@pytest.mark.parametrize("x, y", [(13.0, 9.0), (12.5, 20.5), (16.0, 10.5)])
def test_map_is_symmetric_about_the_keypoint(x, y):
    maps = render_heatmaps(torch.tensor([[[x, y]]]), MAP_SIZE, sigma=1.5)[0, 0]
    r = 6  # px either side; the window's centre is the keypoint (a pixel centre or between two)
    cols = slice(math.floor(x) - r, math.ceil(x) + r + 1)
    rows = slice(math.floor(y) - r, math.ceil(y) + r + 1)
    window = maps[rows, cols]
    assert torch.equal(window, window.flip(0))
    assert torch.equal(window, window.flip(1))
    if (x, y) == (12.5, 20.5):  # between four pixel centres: all four hold the peak, 0.5 px away on each axis
        peak = maps[20:22, 12:14]
        assert torch.equal(peak, torch.full((2, 2), maps.max().item()))
        assert maps.max().item() == pytest.approx(math.exp(-0.5 / (2 * 1.5**2)), rel=1e-6)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 3.0])
def test_sigma_sets_the_width(sigma):
    x, y = 15, 14
    maps = render_heatmaps(torch.tensor([[[float(x), float(y)]]]), MAP_SIZE, sigma)[0, 0]
    s = int(sigma)
    for dx, dy in [(s, 0), (-s, 0), (0, s), (0, -s)]:
        assert maps[y + dy, x + dx].item() == pytest.approx(math.exp(-0.5), rel=1e-6)
    assert maps[y + s, x + s].item() == pytest.approx(math.exp(-1.0), rel=1e-6)
    assert maps[y, x + 1].item() == pytest.approx(math.exp(-1 / (2 * sigma**2)), rel=1e-6)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_the_tails_are_zero_and_no_value_is_a_subnormal_float(sigma):
    # Beyond exp(-TAIL) a profile is 0: far from its keypoint a map is exactly 0, never a
    # subnormal float (which costs a CPU 10x to make), and near it the Gaussian itself.
    from cuboidtrain.models.codec import TAIL

    keypoints = torch.tensor([[[0.0, 0.0], [31.0, 31.0], [15.3, 7.8], [-20.0, 40.0]]])
    maps = render_heatmaps(keypoints, MAP_SIZE, sigma)[0]
    assert ((maps == 0) | (maps >= torch.finfo(torch.float32).tiny)).all()
    grid = torch.arange(MAP_SIZE, dtype=torch.float64)
    for n, (x, y) in enumerate(keypoints[0].double().tolist()):
        ex, ey = (-((grid - x) ** 2) / (2 * sigma**2)), (-((grid - y) ** 2) / (2 * sigma**2))
        exact = torch.exp(ey[:, None]) * torch.exp(ex[None, :])
        inside = (ey[:, None] >= -TAIL) & (ex[None, :] >= -TAIL)
        torch.testing.assert_close(maps[n].double()[inside], exact[inside], rtol=1e-5, atol=1e-30)
        assert (maps[n][~inside] == 0).all()
    assert (maps[0, 31, :] == 0).all() and maps[3].max() == 0  # 31 px from (0, 0); a keypoint far outside


def test_each_keypoint_of_a_batch_gets_its_own_map():
    keypoints = torch.tensor([[[3.0, 4.0], [10.0, 11.0]], [[30.0, 2.0], [0.0, 0.0]]])
    maps = render_heatmaps(keypoints, MAP_SIZE, sigma=1.0)
    assert maps.shape == (2, 2, MAP_SIZE, MAP_SIZE)
    for b in range(2):
        for n in range(2):
            x, y = keypoints[b, n].long().tolist()
            assert maps[b, n, y, x] == 1.0


# ---- decoding ---------------------------------------------------------------------------



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
    assert make_codec("tabulator", model).decode(torch.rand(1, 8, 32, 32), tabulated).keypoints is tabulated
    with pytest.raises(ValueError, match="--extractor 'soft'.*tabulator, argmax, centre-of-mass, dark, pdm"):
        make_codec("soft", model)
    for name in EXTRACTORS:
        points = make_codec(name, model).decode(render_heatmaps(tabulated * 31, 32, 1.0), tabulated).keypoints
        assert points.shape == (1, 8, 2)


def test_the_registry_holds_every_extractor_the_options_offer():
    assert tuple(CODECS) == EXTRACTORS  # settings.EXTRACTORS is the command line's list, without torch
    assert all(CODECS[name].name == name for name in CODECS)


@pytest.mark.parametrize("name", EXTRACTORS)
def test_every_codec_encodes_the_training_target_and_decodes_with_its_extractor(name):
    model = with_generated_pdm(tiny_model("box", SIZE))
    codec = make_codec(name, model)
    truth = torch.from_numpy(generated_sets("box", 2, seed=4))  # valid boxes, which the PDM keeps
    maps = codec.encode(truth)
    assert torch.equal(maps, render_heatmaps(truth, SIZE, model.sigma))  # one encoding for all
    decoded = codec.decode(maps, truth.float())
    assert isinstance(decoded, Decoded) and decoded.keypoints.shape == decoded.scores.shape + (2,) == (2, 8, 2)
    kernel = {"tabulator": lambda m: truth.float(), "argmax": argmax, "centre-of-mass": centre_of_mass,
              "dark": lambda m: dark(m, sigma=model.sigma)}
    if name in kernel:  # the codec is its extractor, nothing added
        assert torch.equal(decoded.keypoints, kernel[name](maps))
    assert distances(decoded.keypoints, truth).max() < (1.0 if name in ("argmax", "pdm") else 0.2)


def test_scores_are_each_maps_peak():
    codec = make_codec("argmax", tiny_model("box", SIZE))
    maps = torch.cat([0.7 * render_heatmaps(random_peaks(1)[:1, :1], SIZE, 2.0), torch.zeros(1, 1, SIZE, SIZE)], 1)
    scores = codec.decode(maps).scores
    assert scores.shape == (1, 2) and scores[0, 1] == 0 and 0.6 < scores[0, 0] <= 0.7


def test_default_sigma_is_size_over_128_and_at_least_a_pixel():
    assert [default_sigma(s) for s in (64, 128, 256, 512)] == [1.0, 1.0, 2.0, 4.0]
    assert tiny_model("box", 256).sigma == 2.0  # a model built without one takes the default


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
    with pytest.raises(ValueError, match=f"--pdm-components {text!r}: expected a count"):
        parse_components(text)


def test_a_pdm_needs_enough_well_formed_sets():
    with pytest.raises(ValueError, match=f"999 keypoint sets: a PDM needs at least {MIN_SAMPLES}"):
        PointDistributionModel.fit(np.zeros((999, 8, 2)))
    with pytest.raises(ValueError, match=r"shape \(1000, 8\): expected \(M, N, 2\)"):
        PointDistributionModel.fit(np.zeros((1000, 8)))


def test_twobox_pdm_and_extractor_on_true_maps():
    model = with_generated_pdm(tiny_model("twobox", SIZE))
    truth = torch.from_numpy(generated_sets("twobox", 4, seed=3))
    points = make_codec("pdm", model, pdm_components="0.999").decode(render_heatmaps(truth, SIZE, 1.0)).keypoints
    assert points.shape == truth.shape and distances(points, truth).mean() < 0.6


def test_the_cli_offers_every_extractor_and_the_library_default():
    from cuboidtrain import cli
    from cuboidtrain.fit import options
    from cuboidtrain.models import settings

    assert [choice.value for choice in cli.ExtractorChoice] == list(settings.EXTRACTORS)
    assert [choice.value for choice in cli.FitShape] == list(options.FIT_SHAPES)
    assert float(typer_default(cli.infer, "pdm_components")) == settings.DEFAULT_PDM_COMPONENTS
    assert typer_default(cli.infer, "margin") == options.DEFAULT_MARGIN


def test_a_model_without_a_pdm_says_how_to_get_one():
    with pytest.raises(ValueError, match="carries no point distribution model.*--pdm-spool"):
        make_codec("pdm", tiny_model("box", 32))


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
