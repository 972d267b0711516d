"""The soft-rasterised silhouette fit (`cuboidtrain.geometry.soft_mask_fit`), the optimiser measured
against LM: its torch projection is `geometry.project`, and on an exact mask it brings perturbed
corners back onto the outline, as a drop-in CuboidFit."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cuboidgen.config import SCENES
from cuboidgen.scene import draw_view
from cuboidtrain.fit.cuboid import check_finite
from cuboidtrain.geometry.camera_params import from_sample_params, outline_corners, project, ratios
from cuboidtrain.geometry.soft_mask_fit import SoftSchedule, fit_soft, torch_project, torch_ratios, unbiased_shift
from shared.raster import rasterize
from shared.shapes import get_shape

SHAPES = ("box", "twobox")


def views(shape: str, count: int, size: int, seed: int):
    rng = np.random.default_rng(seed)
    return [draw_view(get_shape(shape), SCENES["paper"], size, rng) for _ in range(count)]


@pytest.mark.parametrize("shape", SHAPES)
def test_the_torch_projection_is_geometry_project(shape):
    geometry, rng = get_shape(shape), np.random.default_rng(3)
    for view in views(shape, 4, 256, seed=5):
        base = from_sample_params(geometry, view.params).vector
        params = base + rng.normal(0, 0.2, (6, len(base)))
        params[0, 2:5] = 1e-10  # a rotation at the small-angle branch
        mirrors = np.arange(6) % 2 == 0
        image = torch_project(torch.tensor(params), geometry, torch.tensor(mirrors)).numpy()
        assert np.abs(image - project(params, geometry, mirrors)).max() < 1e-9
        assert np.allclose(torch_ratios(torch.tensor(params), geometry).numpy(), ratios(params, geometry), rtol=1e-12)


def test_the_shift_puts_a_blurred_edge_where_the_weighted_cross_entropy_balances():
    u = unbiased_shift(1.0, 0.5)
    assert 0.5 * math.log1p(math.exp(u)) == pytest.approx(math.log1p(math.exp(-u)), rel=1e-9)
    assert unbiased_shift(1.0, 1.0) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("shape", SHAPES)
def test_on_an_exact_mask_perturbed_corners_come_back_onto_the_outline(shape):
    """Corners 1.5 px off (std) on a clean 96 px mask: the fit's outline corners within 1 px."""
    geometry, rng = get_shape(shape), np.random.default_rng(11)
    view = views(shape, 1, 96, seed=2)[0]
    mask = rasterize(geometry, view.keypoints, 96)
    start = view.keypoints + rng.normal(0, 1.5, view.keypoints.shape)
    result = fit_soft(mask, geometry, start, np.ones(len(start)), schedule=SoftSchedule(iterations=60))
    fit = result.fit
    check_finite(fit)  # a drop-in for fit_mask's CuboidFit: every number the record needs is finite
    assert fit.shape == shape and fit.keypoints.shape == view.keypoints.shape
    assert fit.camera.vector.shape == (11 if shape == "box" else 13,) and fit.iou > 0.95
    hull = outline_corners(geometry, view.keypoints)
    before = np.linalg.norm(start - view.keypoints, axis=1)[hull].mean()
    after = np.linalg.norm(fit.keypoints - view.keypoints, axis=1)[hull]
    assert after.mean() < 1.0 and after.mean() < before
