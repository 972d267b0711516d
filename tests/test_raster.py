"""The rasteriser's convention: a pixel is inside when its centre is (docs/contract.md, "Coordinates: pixel centres")."""
import numpy as np
import pytest

from shared.raster import fill_convex, rasterize
from shared.shapes import BOX, TWOBOX


def centres_inside(polygon: np.ndarray, size: int) -> np.ndarray:
    """Reference: pixel centres on the inner side of every edge of a convex polygon (brute force)."""
    ys, xs = np.mgrid[0:size, 0:size]
    sides = []
    for p, q in zip(polygon, np.roll(polygon, -1, axis=0)):
        sides.append((q[0] - p[0]) * (ys - p[1]) - (q[1] - p[1]) * (xs - p[0]))
    sides = np.array(sides)
    return (sides >= 0).all(axis=0) | (sides <= 0).all(axis=0)


def test_known_square_fills_exactly_its_pixel_centres():
    mask = np.zeros((8, 8), bool)
    fill_convex(mask, np.array([[1.5, 1.5], [4.5, 1.5], [4.5, 4.5], [1.5, 4.5]]))
    expected = np.zeros((8, 8), bool)
    expected[2:5, 2:5] = True  # centres 2, 3, 4 lie inside [1.5, 4.5]; 1 and 5 sit on no side
    assert (mask == expected).all()


def test_half_pixel_shift_moves_the_fill_by_one_pixel():
    a, b = np.zeros((8, 8), bool), np.zeros((8, 8), bool)
    square = np.array([[1.4, 1.4], [4.4, 1.4], [4.4, 4.4], [1.4, 4.4]])
    fill_convex(a, square)
    fill_convex(b, square + 0.2)  # 1.6..4.6: centres 2..4 on both sides, same as 1.4..4.4 gives 2..4
    assert a.sum() == 9 and (a == b).all()
    fill_convex(c := np.zeros((8, 8), bool), square - 0.5)  # 0.9..3.9 -> centres 1..3
    assert (np.argwhere(c).min(axis=0) == 1).all() and (np.argwhere(c).max(axis=0) == 3).all()


def test_known_triangle_includes_centres_on_its_edges():
    mask = np.zeros((8, 8), bool)
    fill_convex(mask, np.array([[1.0, 1.0], [5.0, 1.0], [1.0, 5.0]]))
    ys, xs = np.nonzero(mask)
    assert ((xs - 1) + (ys - 1) <= 4).all() and xs.min() == 1 and ys.min() == 1 and mask.sum() == 15


def test_random_convex_polygons_match_brute_force(rng):
    import cv2

    for _ in range(300):
        points = rng.uniform(-6, 38, size=(int(rng.integers(3, 9)), 2))
        hull = points[cv2.convexHull(points.astype(np.float32), returnPoints=False).ravel()]
        if len(hull) < 3:
            continue
        mask = np.zeros((32, 32), bool)
        fill_convex(mask, points)
        assert (mask == centres_inside(hull, 32)).all()


def test_polygons_outside_the_image_fill_nothing():
    mask = np.zeros((16, 16), bool)
    fill_convex(mask, np.array([[-9.0, -9.0], [-2.0, -9.0], [-2.0, -2.0]]))
    fill_convex(mask, np.array([[20.0, 3.0], [30.0, 3.0], [25.0, 9.0]]))
    assert not mask.any()


def test_twobox_silhouette_is_the_union_of_its_parts(rng):
    k = rng.uniform(8, 56, size=(14, 2))
    union = rasterize(TWOBOX, k, 64)
    parts = [np.zeros((64, 64), bool) for _ in TWOBOX.parts]
    for mask, part in zip(parts, TWOBOX.parts):
        fill_convex(mask, k[list(part)])
    assert (union == (parts[0] | parts[1])).all()


@pytest.mark.parametrize("size", [32, 64, 256])
def test_box_silhouette_is_the_hull_of_its_corners(size, rng):
    k = rng.uniform(0, size - 1, size=(8, 2))
    mask = rasterize(BOX, k, size)
    assert mask.dtype == bool and mask.shape == (size, size) and mask.any()
