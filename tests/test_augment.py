"""Occlusion and contour noise: they only remove what they should, and by the amount recorded."""
from dataclasses import replace

import numpy as np
import pytest

from cuboidgen.config import PAPER
from cuboidgen.noise import roughen
from cuboidgen.occlusion import occlude, subtract
from tests.conftest import build_sample


def disc(size=96, radius=30):
    ys, xs = np.mgrid[0:size, 0:size]
    return (xs - size / 2) ** 2 + (ys - size / 2) ** 2 <= radius**2


def test_occlusion_only_removes_pixels(library, rng):
    mask = disc()
    scene = replace(PAPER, occluders=(2, 3))
    out, placed = occlude(mask, library, scene, rng)
    assert len(placed) in (2, 3)
    assert not (out & ~mask).any() and out.sum() < mask.sum()
    assert all(p["kind"] in library.names for p in placed)


def test_no_occluders_leaves_the_mask(library, rng):
    out, placed = occlude(disc(), library, replace(PAPER, occluders=(0, 0)), rng)
    assert placed == [] and (out == disc()).all()


def test_subtract_places_the_cutout_foot_where_asked():
    mask = np.ones((64, 64), bool)
    block = np.ones((10, 4), np.uint8)  # 10 px tall, 4 wide
    subtract(mask, block, {"height_px": 20.0, "angle_deg": 0.0, "flip": False, "x": 30.0, "foot_y": 50.0})
    rows, cols = np.nonzero(~mask)
    assert rows.max() == 50 and 30 <= rows.min() <= 32  # 20 px tall, standing on row 50
    assert abs(cols.mean() - 30.0) < 0.6 and 7 <= np.ptp(cols) + 1 <= 9  # 8 px wide, centred on x = 30


def test_zero_noise_is_the_identity(rng):
    assert (roughen(disc(), 0.0, 6.0, rng) == disc()).all()


@pytest.mark.parametrize("amount", [0.5, 1.5, 3.0])
def test_noise_changes_the_boundary_by_about_the_amount(amount, rng):
    mask = disc(128, 40)
    noisy = roughen(mask, amount, 6.0, rng)
    changed = (noisy != mask).sum()
    perimeter = 2 * np.pi * 40
    # Pixels that changed side per boundary pixel track the mean absolute displacement (0.8 sigma).
    assert 0.4 * amount < changed / perimeter < 1.6 * amount + 0.3
    assert abs(int(noisy.sum()) - int(mask.sum())) < 0.6 * changed + perimeter * 0.1  # unbiased: no net growth


def test_noise_keeps_holes_open(rng):
    mask = disc(96, 36) & ~disc(96, 12)
    noisy = roughen(mask, 1.0, 6.0, rng)
    assert not noisy[48, 48] and noisy[48, 48 + 24]


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_recorded_occluded_fraction_is_the_share_of_the_silhouette_the_occluders_removed(library, shape):
    """Without contour noise the input is the occluded silhouette itself, so the share of clean
    pixels missing from it is the recorded `occluded_fraction`, exactly; with noise (the same seed:
    the same pose and occluders) the recorded fraction is the same and the noise moves the missing
    share by at most the pixels it changed. No occluder placed: nothing removed, fraction 0."""
    quiet = replace(PAPER, occluders=(0, 3), contour_noise=(0.0, 0.0))
    loud = replace(quiet, contour_noise=(3.0, 3.0))
    occluded = 0
    for seed in range(12):
        q = build_sample(seed, shape, size=64, library=library, scene=quiet)
        p = q.params
        clean = int(q.clean.sum())
        assert not (q.noisy & ~q.clean).any() and p["contour_noise"] == 0  # occlusion only removes
        measured = 1.0 - int(q.noisy.sum()) / clean
        assert p["occluded_fraction"] == pytest.approx(measured, abs=1e-12), seed
        if p["occluders"] == []:
            assert p["occluded_fraction"] == 0 and (q.noisy == q.clean).all()
        occluded += p["occluded_fraction"] > 0.01
        n = build_sample(seed, shape, size=64, library=library, scene=loud)
        assert (n.clean == q.clean).all() and n.params["occluders"] == p["occluders"]
        assert n.params["occluded_fraction"] == p["occluded_fraction"]
        assert n.params["contour_noise"] == pytest.approx(3.0 * 64 / 256)
        changed = int((n.noisy != q.noisy).sum())
        assert 0 < changed and abs((1.0 - int((n.clean & n.noisy).sum()) / clean) - measured) <= changed / clean
    assert occluded >= 4  # the occluders did cover part of the building in several samples


def test_contour_normals_match_the_neighbour_differences():
    """The table lookup gives each contour point the unit normal of its two neighbours on
    its own (wrapped) contour; one- and two-point contours get none."""
    import cv2

    from cuboidgen.noise import contour_normals

    mask = disc(96, 36) & ~disc(96, 12)
    mask[5, 5] = mask[5, 8] = mask[6, 8] = True  # a one-point and a two-point contour
    mask[80:84, 2:90:7] = True  # a row of small blobs
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    lengths = [len(c) for c in contours]
    assert {1, 2} <= set(lengths) and len(contours) > 10
    points = np.concatenate(contours).reshape(-1, 2)
    got = contour_normals(points.view(np.int64).ravel(), lengths)
    expected, start = [], 0
    for n in lengths:
        p = points[start : start + n].astype(float)
        d = np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)
        norm = np.hypot(d[:, 0], d[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            expected.append(np.where(norm > 0, (d[:, 1] - 1j * d[:, 0]) / norm, 0))
        start += n
    assert np.allclose(got, np.concatenate(expected), atol=1e-12)


def test_occlusion_matches_warping_each_cutout_over_the_whole_image(library):
    """The fast path (inverted cutouts made once, warped into the silhouette's box only)
    clears exactly the pixels a whole-image warp of each recorded placement covers."""
    import cv2

    from cuboidgen.occlusion import placement_affine

    mask = disc(96, 30)
    mask[10:20, 70:90] = True  # a second piece, so the box is not the disc's
    scene = replace(PAPER, occluders=(3, 3), grounded_probability=0.5)
    hit = 0
    for seed in range(30):
        out, placed = occlude(mask, library, scene, np.random.default_rng(seed))
        expected = mask.copy()
        for p in placed:
            cutout = library.masks[p["index"]]
            a, b, tx, c, d, ty = placement_affine(cutout.shape, p)
            warped = cv2.warpAffine(cutout, np.array([[a, b, tx], [c, d, ty]]), mask.shape[::-1], flags=cv2.INTER_NEAREST)
            expected &= warped == 0
        assert (out == expected).all(), seed
        hit += bool((out != mask).any())
    assert hit > 20
