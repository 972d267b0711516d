"""A sample framed as `infer` frames a mask (train as you infer; issue 29): its building (the
noisy mask's pieces that `cuboidtrain.fit.masks.silhouette` keeps), framed at the model's size
by `cuboidtrain.fit.masks.framing_of`, its keypoints carried into the model's px. Only numbers
here: the pixels are framed on the device (`cuboidtrain.data.device_framing`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from cuboidtrain.fit.masks import PIECE_SHARE, Framing, framing_of
from cuboidtrain.fit.options import DEFAULT_MARGIN
from shared.sample import PackedSample, pack_mask

# A reframed sample whose corner lies further than this fraction of the size outside the frame is
# skipped: what is visible of it is a fragment, and no Tabulator could reach the corner.
MAX_OUTSIDE = 0.125


class CutOff(Exception):
    """A sample whose visible part cannot frame the whole shape (see MAX_OUTSIDE)."""


@dataclass(frozen=True, slots=True)
class Framed:
    """A sample framed at the model's size: `sample`'s noisy mask is its building's pixels (at the
    sample's own size) and its keypoints are in the model's px; `framing` maps the sample's px to the
    model's (`prepare_batch` carries both masks by it)."""

    sample: PackedSample
    framing: Framing


def identity_framing(size: int) -> Framing:
    """The framing of a sample kept at its own `size`: the model's px are its own."""
    return Framing(1.0, (0.0, 0.0), size, (size, size))


def building_and_box(mask: np.ndarray, min_share: float = PIECE_SHARE, min_pixels: int = 16):
    """`cuboidtrain.fit.masks.silhouette` of a uint8 0/1 mask, the same pixels, and their bounding
    box (x, y, w, h); None when no piece is kept. The mask itself (no copy) when every piece is.
    tests/test_data.py pins it to `silhouette` pixel for pixel.

    From the pieces' borders (`cv2.findContours`) rather than a labelling: 6x faster at 256 px.
    A piece's pixels are those its outer border walk encloses (Pick: area + steps / 2 + 1) less
    the pixels inside each of its holes' walks (area - steps / 2 + 1)."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    parent, pixels = hierarchy[0][:, 3].tolist(), [0.0] * len(contours)
    for i, contour in enumerate(contours):
        area, steps = abs(cv2.contourArea(contour)), (len(contour) if len(contour) > 1 else 0)
        if parent[i] < 0:
            pixels[i] += area + steps / 2 + 1
        else:
            pixels[parent[i]] -= area - steps / 2 + 1
    outer = [i for i in range(len(contours)) if parent[i] < 0]
    largest = max(pixels[i] for i in outer)
    if largest < min_pixels:
        return None
    least = max(min_pixels, min_share * largest)
    kept = [i for i in outer if pixels[i] >= least]
    boxes = [cv2.boundingRect(contours[i]) for i in kept]
    x, y = min(b[0] for b in boxes), min(b[1] for b in boxes)
    box = (x, y, max(b[0] + b[2] for b in boxes) - x, max(b[1] + b[3] for b in boxes) - y)
    if len(kept) == len(outer):
        return mask, box
    return _without(mask, contours, hierarchy[0], [i for i in outer if pixels[i] < least], pixels), box


def _without(mask: np.ndarray, contours, links: np.ndarray, dropped: list[int], pixels: list[float]) -> np.ndarray:
    """`mask` less its `dropped` pieces (outer borders of `contours`, `links` their hierarchy)."""
    if all(links[i][2] < 0 for i in dropped):  # no dropped piece has a hole another piece could lie in
        kept = mask.copy()
        cv2.drawContours(kept, [contours[i] for i in dropped], -1, 0, thickness=cv2.FILLED)
        return kept
    # Each outer border filled with 1 (kept) or 0, larger fills first: a piece inside another's hole wins.
    canvas, outer = np.zeros_like(mask), [i for i in range(len(contours)) if links[i][3] < 0]
    for i in sorted(outer, key=lambda i: -pixels[i]):
        cv2.drawContours(canvas, contours, i, 0 if i in dropped else 1, thickness=cv2.FILLED)
    return canvas & mask


def framed(sample: PackedSample, size: int, margin: float = DEFAULT_MARGIN) -> Framed:
    """`sample` as `infer` would see it, all but its pixels: its noisy mask's building
    (`building_and_box`: its pieces, together) framed at `size` as `cuboidtrain.fit.masks.frame`
    frames it. A generated sample is framed by its noisy silhouette; a real mask can only be framed
    by what is visible of it. Raises CutOff for a sample no framing of its visible part can hold."""
    noisy = sample.noisy_mask()
    found = building_and_box(noisy)
    if found is None:
        raise CutOff("no visible piece to frame")
    kept, box = found
    framing = framing_of(box, size, margin, (sample.size, sample.size))
    keypoints = framing.to_model(sample.keypoints)
    reach = MAX_OUTSIDE * size
    if keypoints.min() < -0.5 - reach or keypoints.max() > size - 0.5 + reach:
        raise CutOff(f"a corner lies more than {reach:g} px outside the frame")
    bits = sample.noisy if kept is noisy else pack_mask(kept)
    return Framed(dataclasses.replace(sample, noisy=bits, keypoints=keypoints), framing)
