"""Input masks for inference: read them, pick their components, frame them for a model.

`load_mask` turns a PNG or JPG of any size, a file or a URL fsspec reads (`storage`), into a
bool mask (one decoding for both: the bytes are read, then decoded), `components` splits it
into 8-connected objects and `frame` maps one object onto the model's square input
with a single affine map, kept as a `Framing` so that keypoints predicted at the
model's resolution go back to the input image's own pixels. Integer coordinates are
pixel centres in both images (docs/contract.md, "Coordinates: pixel centres"), so the map between them is
`x_model = scale * x_input + offset` with no half-pixel terms anywhere.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cuboidtrain.fit.options import DEFAULT_MARGIN
from cuboidtrain.fit.storage import is_url, read_bytes
from shared.errors import UsageError


def load_mask(path: str | Path, label_id: int | None = None, threshold: float | None = None,
              invert: bool = False) -> np.ndarray:
    """The object pixels of a mask image file or URL as a bool (H, W) array (`to_mask`'s rules)."""
    path = path if is_url(path) else Path(path)  # a Path would fold a URL's `//`
    return to_mask(_read(path), label_id, str(path), threshold, invert)


def to_mask(image: np.ndarray, label_id: int | None = None, source: str = "mask",
            threshold: float | None = None, invert: bool = False) -> np.ndarray:
    """The object pixels of a decoded mask image (H, W) or (H, W, C) as a bool (H, W) array.

    The rule (docs/inference.md, "What a mask is"): an image's levels are its grey values, its
    alpha channel where that is not constant, or for colour its brightest channel (its grey,
    0.299 R + 0.587 G + 0.114 B, with `threshold` or `invert`). The object is the levels above
    `threshold`, by default half the brightest level (the alpha's half scale): 0/255, 0/1 and
    JPEG-noisy masks alike, a colour on black; `invert` takes the rest. Without `threshold` the
    image must be two-valued: more than MAX_BETWEEN of its pixels between its darkest and brightest
    levels (a photo) is a UsageError naming the share. With `label_id` a grey label map's pixels
    equal to it are the object. An object that covers the whole border (a dark object on a light
    background, read the wrong way round) or every pixel is a UsageError saying which option reads
    it right. `source` names the input in errors.
    """
    image = np.asarray(image)
    if image.dtype == bool:
        image = image.astype(np.uint8)
    if image.ndim not in (2, 3) or image.size == 0:
        raise UsageError(f"{source}: an array of shape {image.shape}, expected an (H, W) or (H, W, C) image")
    if label_id is not None:
        if image.ndim != 2:
            raise UsageError(f"{source}: a label id needs a single-channel label map, "
                             f"got a {image.shape[2]}-channel image")
        mask = image == label_id
        if not mask.any():
            labels = np.unique(image).tolist()
            present = ", ".join(map(str, labels[:12])) + (", ..." if len(labels) > 12 else "")
            raise UsageError(f"{source}: label {label_id} not found in the label map "
                             f"(labels present: {present})")
        if mask.all():
            raise UsageError(f"{source}: every pixel is label {label_id}: no background, so no outline to fit; "
                             f"expected a label map in which the object is one label among others")
        return mask
    levels, half, what = mask_levels(image, explicit=threshold is not None or invert)
    if levels.dtype.kind == "f" and not np.isfinite(levels).all():
        raise UsageError(f"{source}: {np.count_nonzero(~np.isfinite(levels)):,} of its pixels are NaN or infinite "
                         f"in {what}; expected finite levels")
    if threshold is None:
        check_two_valued(levels, source, what)
    cut = half if threshold is None else threshold
    mask = levels > cut if threshold is not None or levels.max() > 0 else np.zeros(levels.shape, bool)
    if invert:
        mask = ~mask
    side = f"pixels {'at or below' if invert else 'above'} {_level(cut)} in {what}"
    if not mask.any():
        raise UsageError(f"{source}: empty mask: no object pixels (the object: {side}, which span "
                         f"{_level(levels.min())} to {_level(levels.max())})")
    check_background(mask, source, side, threshold is not None, invert)
    return mask


# The share of a mask's pixels that may lie between its two values (further than a quarter of the
# way from both): JPEG ringing and anti-aliased edges. Measured: a JPEG of quality 10 at 0.7% (2.4%
# for a 50 x 60 px one), a mask shrunk to a tenth with INTER_AREA 4.8%; a photograph 27%.
MAX_BETWEEN = 0.10


def mask_levels(image: np.ndarray, explicit: bool = False) -> tuple[np.ndarray, float, str]:
    """What `to_mask` cuts: (levels (H, W), the default cut, a name for them in errors). A varying
    alpha is the cut-out itself (the colour under a transparent pixel is arbitrary), cut at half
    its scale; grey is itself; colour is its brightest channel ("any non-black colour"), or with
    `explicit` (a threshold or invert given) its grey, so a colour on white can be told apart."""
    if image.ndim == 3 and image.shape[2] == 4 and image[..., 3].min() != image[..., 3].max():
        top = np.iinfo(image.dtype).max if image.dtype.kind in "ui" else 1.0
        return image[..., 3], top / 2, "its alpha channel"
    if image.ndim == 2:
        return image, image.max() / 2, "its grey levels"
    if explicit and image.shape[2] >= 3:
        colour = np.ascontiguousarray(image[..., :3])  # BGR, OpenCV's order
        if colour.dtype in (np.uint8, np.uint16, np.float32):  # in the image's own type: 100 Mpx stay 100 MB
            grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
        else:
            grey = colour.astype(np.float32) @ np.float32([0.114, 0.587, 0.299])
        return grey, grey.max() / 2, "its grey levels (0.299 R + 0.587 G + 0.114 B)"
    # Half the maximum serves 0/1 and 0/255 masks alike and drops JPEG ringing near black.
    grey = image[..., :3].max(axis=2)
    return grey, grey.max() / 2, "its brightest colour channel"


def check_two_valued(levels: np.ndarray, source: str, what: str) -> None:
    """A UsageError when more than MAX_BETWEEN of the pixels lie between the darkest and the
    brightest level (each further than a quarter of the range from both): not a binary mask."""
    low, high = float(levels.min()), float(levels.max())
    span = high - low
    if span <= 0:
        return
    between = np.count_nonzero((levels > low + span / 4) & (levels < high - span / 4)) / levels.size
    if between > MAX_BETWEEN:
        raise UsageError(f"{source}: not a binary mask: {between:.0%} of its pixels lie between its darkest "
                         f"({_level(low)}) and brightest ({_level(high)}) values in {what}, as in a photo; "
                         f"expected two values, object and background (at most {MAX_BETWEEN:.0%} between), "
                         f"or --threshold T to cut it at level T (--invert: the dark side is the object)")


def check_background(mask: np.ndarray, source: str, side: str, threshold: bool, invert: bool) -> None:
    """A UsageError when the object has no background around it: it is every pixel, or it covers the
    whole border (the background is enclosed, or absent): the mask is read the wrong way round."""
    border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
    if not border.all():
        return
    flip = "drop --invert" if invert else "pass --invert"
    fix = f"{flip} if the other side is the object" + ("" if threshold else ", or --threshold T")
    if mask.all():
        raise UsageError(f"{source}: every pixel is the object ({side}): no background, so no outline to fit; "
                         f"expected an object on a background: {fix}")
    raise UsageError(f"{source}: the object ({side}) covers the whole border and encloses the rest, as the "
                     f"background of a dark object on a light one would; expected the object inside a "
                     f"background that reaches the border: {fix}")


def _level(value) -> str:
    """A level as errors show it: 255, 0.5, 127.5."""
    return f"{float(value):g}"


MAX_PIXELS = 100_000_000  # 10,000 x 10,000: a decoded mask plus its labels then take about 0.6 GB


def _read(path: str | Path) -> np.ndarray:
    # imdecode from bytes: cv2.imread fails silently on some non-ASCII paths, and reads no URL.
    try:
        data = read_bytes(path)
    except OSError as error:
        raise UsageError(f"{path}: cannot read image ({error.strerror or error})") from None
    try:
        declared = declared_size(memoryview(data))
    except ValueError as error:
        raise UsageError(f"{path}: cannot read image ({error})") from None
    _check_pixels(path, declared)  # before decoding allocates it
    image = _decode(data) if data.size else None
    if image is None:
        raise UsageError(f"{path}: cannot read image (not a PNG or JPG OpenCV can decode)")
    _check_pixels(path, (image.shape[1], image.shape[0]))  # formats whose header we do not read
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    return image


def _decode(data: np.ndarray) -> np.ndarray | None:
    """The decoded image, or None; OpenCV's own warnings (a truncated PNG's "[ WARN ...] buffer is
    incomplete") are not printed: a file it cannot decode gets its one-line error, in its record."""
    from cv2.utils import logging as cv2_logging

    level = cv2_logging.getLogLevel()
    cv2_logging.setLogLevel(cv2_logging.LOG_LEVEL_ERROR)
    try:
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        cv2_logging.setLogLevel(level)


def _check_pixels(path: str | Path, size: tuple[int, int] | None) -> None:
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise UsageError(f"{path}: image of {size[0]} x {size[1]} px is too large: at most {MAX_PIXELS:,} px "
                         f"(downscale the mask first; the model sees it at 64-256 px anyway)")


# JPEG markers that stand alone, without a length: TEM, RST0-7, SOI, EOI.
_STANDALONE = frozenset({0x01, *range(0xD0, 0xDA)})
_START_OF_SCAN = 0xDA  # entropy-coded data follows: every frame header comes before it


def declared_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame header; None if neither format.

    A JPEG's frame header may lie anywhere before its first scan, after any number of APPn
    segments (an ICC profile, EXIF, XMP: megabytes, in 64 KB chunks), so the segments are walked
    by their lengths, reading 4 bytes of each, never decoding. A JPEG whose frame header cannot be
    found that way is a ValueError: it is either not a JPEG or one OpenCV would refuse anyway,
    and its size cannot be checked before decoding."""
    if bytes(data[:8]) == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if bytes(data[:2]) != b"\xff\xd8":
        return None
    position = 2
    while position + 1 < len(data) and data[position] == 0xFF:
        marker = data[position + 1]
        if marker == 0xFF:  # a fill byte before a marker
            position += 1
            continue
        if marker in _STANDALONE:
            position += 2
            continue
        if marker == _START_OF_SCAN or position + 4 > len(data):
            break
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn, not DHT/JPG/DAC
            if position + 9 > len(data):
                break
            return (int.from_bytes(data[position + 7 : position + 9], "big"),
                    int.from_bytes(data[position + 5 : position + 7], "big"))
        position += 2 + int.from_bytes(data[position + 2 : position + 4], "big")
    raise ValueError(f"a JPEG without a frame header before its image data (stopped at byte {position} of "
                     f"{len(data)}), so its size cannot be checked before decoding")


def components(mask: np.ndarray, all_components: bool = False, min_pixels: int = 16) -> list[np.ndarray]:
    """The largest 8-connected component of `mask` as a bool mask of the same shape, or
    with `all_components` every component of at least `min_pixels` pixels, largest first.
    An empty mask has no components."""
    labels, order, areas = _labelled(mask)
    if not all_components:
        order = order[:1]
    else:
        order = [k for k in order if areas[k] >= min_pixels]
    return [labels == k for k in order]


def _labelled(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8-connected labels of `mask`, the labels largest first (background 0 left out), and
    each label's area (indexed by label)."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    areas = stats[:, cv2.CC_STAT_AREA]
    return labels, np.argsort(-areas[1:], kind="stable") + 1, areas


# A piece of a one-building mask at least this share of its largest piece's area is part of the
# building: an occluder (a pole, a car, a tree) cuts a silhouette into pieces, and framing only
# the largest one fits a fragment. Smaller specks are segmentation noise. Measured through infer
# on 300 generated 256 px masks per set with the shipped models (BENCHMARKS.md): mean corner
# error 13.4 -> 9.3 px on `street` box, 17.1 -> 12.0 on noisy `paper` twobox; 5% kept less.
PIECE_SHARE = 0.01


def silhouette(mask: np.ndarray, min_share: float = PIECE_SHARE, min_pixels: int = 16) -> np.ndarray | None:
    """The building of a one-building mask, as a bool mask of the same shape: every 8-connected
    piece of at least `min_pixels` pixels and `min_share` of the largest piece's area, together.
    None when the mask has no such piece."""
    labels, order, areas = _labelled(mask)
    if not len(order) or areas[order[0]] < min_pixels:
        return None
    least = max(min_pixels, min_share * areas[order[0]])  # the areas the labelling counted: no mask summed again
    return np.isin(labels, [k for k in order if areas[k] >= least])


@dataclass(frozen=True)
class Framing:
    """The affine map from an input image's pixels to the model's `size` x `size` input:
    `model = scale * input + offset`, per axis, in pixel-centre coordinates."""

    scale: float  # model px per input px
    offset: tuple[float, float]  # model px (x, y)
    size: int  # model input side, px
    input_shape: tuple[int, int]  # (height, width) of the input image, px

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) input-image (x, y) -> (N, 2) model-input (x, y)."""
        return np.asarray(points, dtype=np.float64) * self.scale + np.asarray(self.offset)

    def to_input(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) model-input (x, y) -> (N, 2) input-image (x, y); the inverse of to_model."""
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.offset)) / self.scale

    @property
    def matrix(self) -> np.ndarray:
        """The 2x3 input -> model matrix, as cv2.warpAffine takes it."""
        (tx, ty), s = self.offset, self.scale
        return np.array([[s, 0.0, tx], [0.0, s, ty]])


def frame(mask: np.ndarray, size: int, margin: float = DEFAULT_MARGIN,
          grey: bool = False) -> tuple[np.ndarray, Framing]:
    """Scale and centre the object of `mask` so its longer side spans the model input
    less two margins (fraction of `size`, each side, in [0, 0.5) as FitOptions checks,
    as the generator frames its scenes); returns the (size, size) model input and its
    Framing. The input is bool, or with `grey` the float32 share of each model pixel the
    object covers (`coverage`)."""
    if not mask.any():
        raise ValueError("cannot frame an empty mask")
    box = cv2.boundingRect(mask.astype(np.uint8))
    framing = framing_of(box, size, margin, mask.shape[:2])
    return levels(_warp(mask, box, framing), grey), framing


def framing_of(box: tuple[int, int, int, int], size: int, margin: float, shape: tuple[int, int]) -> Framing:
    """The Framing `frame` gives an object whose bounding box is `box` (x, y, w, h) in an image of
    `shape` (height, width): its longer side spans `size` less two margins. The trainer's loader
    frames a sample's building by it too (`cuboidtrain.data.reframing.framed`)."""
    x, y, w, h = box
    # Pixels x .. x + w - 1 cover [x - 0.5, x + w - 0.5]: w px wide, centred on x + (w - 1) / 2,
    # as the generator centres a polygon's extent on the model's middle pixel (size - 1) / 2.
    scale = size * (1 - 2 * margin) / max(w, h)
    offset = ((size - 1) / 2 - scale * (x + (w - 1) / 2), (size - 1) / 2 - scale * (y + (h - 1) / 2))
    return Framing(float(scale), (float(offset[0]), float(offset[1])), size, shape)


def warp(mask: np.ndarray, framing: Framing, grey: bool = False) -> np.ndarray:
    """All of `mask` carried onto the model's input by `framing`, as `frame` carries its
    object (training frames the clean silhouette by its noisy one's framing)."""
    height, width = mask.shape
    return levels(_warp(mask, (0, 0, width, height), framing), grey)


def levels(coverage: np.ndarray, grey: bool) -> np.ndarray:
    """A model input from the share of each model pixel the object covers: bool (half covered
    or more), or with `grey` the share itself, in [0, 1]. A grey input keeps where an edge lies
    inside a model pixel, which a binary one rounds to the pixel (a 64 px input read at 256 px:
    to within 4 px)."""
    return coverage.clip(0.0, 1.0) if grey else coverage >= 0.5


SHRINK_BLUR = 0.29  # the Gaussian's std when shrinking, in source px per model px (`cuboidtrain.data.device_framing` frames by it too)


def _warp(mask: np.ndarray, box: tuple[int, int, int, int], framing: Framing) -> np.ndarray:
    """The float coverage of `mask` sampled at the model's pixel centres."""
    s = framing.scale
    # Shrinking: a Gaussian with the variance of a 1/s-wide box, then bilinear sampling,
    # approximates INTER_AREA (which warpAffine lacks) without a half-pixel shift.
    sigma = SHRINK_BLUR / s if s < 1 else 0.0
    # Crop to the box plus room for the blur, padded with background so objects that
    # touch the image border are not mirrored or cut by the blur's border rule.
    pad = math.ceil(3 * sigma) + 2
    x, y, w, h = box
    crop = np.zeros((h + 2 * pad, w + 2 * pad), np.float32)
    crop[pad : pad + h, pad : pad + w] = mask[y : y + h, x : x + w]
    if sigma > 0:
        crop = cv2.GaussianBlur(crop, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    # Model pixel (u, v) samples crop pixel ((u - tx) / s - x + pad, ...): the inverse map.
    (tx, ty), origin = framing.offset, (x - pad, y - pad)
    inverse = np.array([[1 / s, 0.0, -tx / s - origin[0]], [0.0, 1 / s, -ty / s - origin[1]]])
    return cv2.warpAffine(crop, inverse, (framing.size, framing.size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
