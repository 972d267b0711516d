"""Device-side targets: heat maps on the pixel-centre convention, packed masks, prepare_batch."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cuboidtrain.train.data import SpoolBatches
from cuboidtrain.fit.heatmaps import prepare_batch, render_heatmaps, unpack_masks
from shared.sample import signed
from shared.shapes import get_shape
from tests.conftest import SIZE as SAMPLE_SIZE
from tests.conftest import build_sample, fill_spool

SIZE = 32  # px
CPU = torch.device("cpu")


def random_keypoints(count: int, margin: float, seed: int = 0) -> torch.Tensor:
    """(1, count, 2) sub-pixel keypoints at least `margin` px inside a SIZE px image."""
    g = torch.Generator().manual_seed(seed)
    return margin + torch.rand(1, count, 2, generator=g, dtype=torch.float64) * (SIZE - 1 - 2 * margin)


# ---- render_heatmaps ------------------------------------------------------------------


def test_peak_is_exactly_one_at_an_integer_keypoint_row_y_column_x():
    keypoints = torch.tensor([[[5.0, 20.0], [20.0, 5.0], [0.0, 31.0]]])  # (x, y)
    maps = render_heatmaps(keypoints, SIZE, sigma=1.5)
    assert maps.shape == (1, 3, SIZE, SIZE) and maps.dtype == torch.float32
    for n, (x, y) in enumerate(keypoints[0].long().tolist()):
        assert maps[0, n, y, x] == 1.0  # row y, column x
        assert maps[0, n].max() == 1.0
        assert (maps[0, n] == 1.0).sum() == 1
        assert divmod(int(maps[0, n].argmax()), SIZE) == (y, x)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_centre_of_mass_of_a_sub_pixel_map_is_the_keypoint(sigma):
    # integers are pixel centres: the map's centre of mass over pixel centres j, i
    # must be the keypoint itself, not the keypoint +- 0.5
    keypoints = random_keypoints(20, margin=4 * sigma, seed=int(sigma * 10))
    maps = render_heatmaps(keypoints, SIZE, sigma).double()[0]  # (20, H, W)
    grid = torch.arange(SIZE, dtype=torch.float64)
    mass = maps.sum(dim=(1, 2))
    com_x = (maps * grid[None, None, :]).sum(dim=(1, 2)) / mass
    com_y = (maps * grid[None, :, None]).sum(dim=(1, 2)) / mass
    err = torch.stack([com_x, com_y], dim=1) - keypoints[0]
    assert err.abs().max() < 0.01, err.abs().max()


def test_argmax_pixel_is_the_rounded_keypoint():
    keypoints = random_keypoints(20, margin=3.0, seed=7)
    maps = render_heatmaps(keypoints, SIZE, sigma=1.0)[0]
    for n, (x, y) in enumerate(keypoints[0].tolist()):
        assert divmod(int(maps[n].argmax()), SIZE) == (round(y), round(x))


@pytest.mark.parametrize("x, y", [(13.0, 9.0), (12.5, 20.5), (16.0, 10.5)])
def test_map_is_symmetric_about_the_keypoint(x, y):
    maps = render_heatmaps(torch.tensor([[[x, y]]]), SIZE, sigma=1.5)[0, 0]
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
    maps = render_heatmaps(torch.tensor([[[float(x), float(y)]]]), SIZE, sigma)[0, 0]
    s = int(sigma)
    for dx, dy in [(s, 0), (-s, 0), (0, s), (0, -s)]:
        assert maps[y + dy, x + dx].item() == pytest.approx(math.exp(-0.5), rel=1e-6)
    assert maps[y + s, x + s].item() == pytest.approx(math.exp(-1.0), rel=1e-6)
    assert maps[y, x + 1].item() == pytest.approx(math.exp(-1 / (2 * sigma**2)), rel=1e-6)


def test_each_keypoint_of_a_batch_gets_its_own_map():
    keypoints = torch.tensor([[[3.0, 4.0], [10.0, 11.0]], [[30.0, 2.0], [0.0, 0.0]]])
    maps = render_heatmaps(keypoints, SIZE, sigma=1.0)
    assert maps.shape == (2, 2, SIZE, SIZE)
    for b in range(2):
        for n in range(2):
            x, y = keypoints[b, n].long().tolist()
            assert maps[b, n, y, x] == 1.0


# ---- unpack_masks ---------------------------------------------------------------------


@pytest.mark.parametrize("size", [32, 48, 33])  # 33: 1089 bits, the last byte padded
def test_unpack_masks_inverts_numpy_packbits(size):
    rng = np.random.default_rng(size)
    masks = rng.random((3, size, size)) < 0.4
    packed = np.packbits(masks.reshape(3, -1), axis=1)
    assert packed.shape == (3, (size * size + 7) // 8)
    out = unpack_masks(torch.from_numpy(packed), size)
    assert out.shape == (3, 1, size, size) and out.dtype == torch.float32
    assert torch.equal(out[:, 0], torch.from_numpy(signed(masks)))


# ---- prepare_batch --------------------------------------------------------------------


def test_prepare_batch_gives_the_samples_own_masks_heatmaps_and_keypoints(tmp_path):
    spool = tmp_path / "spool"
    names = fill_spool(spool, 4)  # seeds 0..3, SAMPLE_SIZE px boxes
    seed_of = {name: seed for seed, name in enumerate(names)}
    batch = SpoolBatches(spool, "box", SAMPLE_SIZE)[names[::-1]]  # a batch in another order than published
    assert batch["names"] == names[::-1]
    sigma = 1.0
    x = prepare_batch(batch, CPU, sigma, SAMPLE_SIZE)
    n = get_shape("box").num_keypoints
    assert x["x1"].shape == x["x2"].shape == (4, 1, SAMPLE_SIZE, SAMPLE_SIZE)
    assert x["x3"].shape == (4, n, SAMPLE_SIZE, SAMPLE_SIZE)
    assert x["x4"].shape == (4, n, 2) and x["ratios"].shape == (4, 2)
    for b, name in enumerate(batch["names"]):
        sample = build_sample(seed_of[name])
        assert torch.equal(x["x1"][b, 0], torch.from_numpy(signed(sample.noisy)))
        assert torch.equal(x["x2"][b, 0], torch.from_numpy(signed(sample.clean)))
        keypoints = torch.from_numpy(sample.keypoints).float()
        assert torch.equal(x["x4"][b], keypoints)
        ratios = get_shape("box").ratio_vector(sample.ratios)
        assert torch.allclose(x["ratios"][b], torch.from_numpy(ratios).float())
        for k, (kx, ky) in enumerate(sample.keypoints.tolist()):
            want = (min(max(round(ky), 0), SAMPLE_SIZE - 1), min(max(round(kx), 0), SAMPLE_SIZE - 1))
            assert divmod(int(x["x3"][b, k].argmax()), SAMPLE_SIZE) == want, (name, k)
    assert torch.equal(x["x3"], render_heatmaps(x["x4"], SAMPLE_SIZE, sigma))
