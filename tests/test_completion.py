"""The Refiner's completion in the cuboid fit (cuboidtrain.fit.completion): what an occluder
hid and the Refiner fills in is excused from the overhang cost and its cut edge leaves the
outline; a Refiner's blurred outline along the input's own adds nothing."""
from dataclasses import replace

import cv2
import numpy as np

from cuboidtrain.fit import completion as stage
from cuboidtrain.fit.masks import frame
from cuboidtrain.geometry.outline import MaskTarget, bilinear
from tests.test_infer import candidate

SIZE = 64  # the Refiner's resolution; the input is 4x that


def square(size: int, lo: int, hi: int) -> np.ndarray:
    mask = np.zeros((size, size), dtype=bool)
    mask[lo:hi, lo:hi] = True
    return mask


def refined_candidate(building: np.ndarray, grow_model_px: int = 0):
    """A box candidate whose Refiner output is `building` framed as the Fitter frames the input,
    grown by `grow_model_px` (a blurred outline), as R's tanh output (+1 building, -1 not)."""
    framed, framing = frame(building, SIZE)
    if grow_model_px:
        framed = np.pad(framed, grow_model_px)[: SIZE, : SIZE] | framed  # shifted copy: a few px wider
        framed = framed | np.roll(framed, grow_model_px, axis=(0, 1))
    return replace(candidate("box", 0.9), refined=np.where(framed, 1.0, -1.0), framing=framing)


def test_an_occluded_part_is_completed_and_its_cut_edge_leaves_the_outline():
    building = square(256, 40, 216)
    seen = building.copy()
    seen[40:120, 150:216] = False  # an occluder took the top right corner
    target = MaskTarget.of(seen)
    completed = stage.completed_target(refined_candidate(building), target)
    assert stage.completion(refined_candidate(building), seen)[60:110, 160:210].all()  # the hidden part's inside
    assert completed.mask is target.mask  # IoU is judged against what was seen
    # Over the hidden part the model's outline costs nothing; inside the input, as before.
    assert (completed.sdf[60:110, 160:210] == 0).all() and np.array_equal(completed.sdf[seen], target.sdf[seen])
    far = ~square(256, 34, 222)  # beyond the completion's few px of blur
    assert (completed.sdf[far] > 0).all()
    # The occluder's edge (x = 149.5, deep inside the building) is no outline any more.
    def on_cut(points):
        return (np.abs(points[:, 0] - 149.5) < 1) & (points[:, 1] > 45) & (points[:, 1] < 115)

    assert on_cut(target.outline).sum() >= 2 and not on_cut(completed.outline).any()
    assert np.abs(bilinear(target.sdf, completed.outline)).max() <= 0.5  # kept points are the input's own outline


def test_a_blurred_outline_along_the_input_adds_nothing():
    building = square(256, 40, 216)
    target = MaskTarget.of(building)
    assert stage.completed_target(refined_candidate(building, grow_model_px=1), target) is target


def test_the_opening_read_near_the_added_pixels_is_the_whole_images():
    """`opened` works on the added pixels' neighbourhood only: the same pixels as OpenCV's opening of the
    whole image, for blobs of any size at the image's edges and far from them, and for none at all."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        height, width = rng.integers(4, 90, 2)
        added = np.zeros((height, width), dtype=np.uint8)
        for _ in range(rng.integers(0, 4)):
            y, x = rng.integers(0, height), rng.integers(0, width)
            added[max(0, y - rng.integers(0, 25)): y + rng.integers(1, 25),
                  max(0, x - rng.integers(0, 25)): x + rng.integers(1, 25)] = 1
        added &= (rng.random((height, width)) > 0.1).astype(np.uint8)  # ragged edges, holes
        radius = int(rng.integers(1, 8))
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        np.testing.assert_array_equal(stage.opened(added, disc, radius),
                                      cv2.morphologyEx(added, cv2.MORPH_OPEN, disc) > 0)
