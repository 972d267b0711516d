"""A batch's masks unpacked and framed on the training device, as `cuboidtrain.fit.masks.warp`
frames one mask (tests/test_data.py pins the two together).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from cuboidtrain.fit.masks import SHRINK_BLUR
from shared.sample import BIT_SHIFTS, unpack_rows

_BIT_SHIFTS = torch.tensor(BIT_SHIFTS, dtype=torch.uint8)  # shared.sample's bit order, one shift per pixel of a byte


def unpack_bits(packed: torch.Tensor, count: int) -> torch.Tensor:
    """(..., n) uint8 packed bits (`shared.sample.pack_mask`'s order) -> (..., count) uint8 0/1 along
    the last axis, on the tensor's device (numpy's unpacking on the CPU: 8x faster than torch's shifts)."""
    if packed.device.type == "cpu":
        return torch.from_numpy(unpack_rows(packed.numpy(), count))
    bits = (packed.unsqueeze(-1) >> _BIT_SHIFTS.to(packed.device)) & 1  # (..., n, 8)
    return bits.flatten(-2)[..., :count]


def unpack_masks(packed: torch.Tensor, size: int) -> torch.Tensor:
    """(B, ceil(size*size/8)) uint8 packed bits -> (B, 1, size, size) float32, +1 object / -1
    background. In torch, so that it runs on the training device."""
    return unpack_bits(packed, size * size).view(-1, 1, size, size).float() * 2 - 1


# ---- framing on the device ----------------------------------------------------------------
# `cuboidtrain.fit.masks.warp` carries a mask onto the model's input by a Framing: a Gaussian of std
# 0.29 / scale px when shrinking (cv2's, of radius round(8 std + 1) // 2 px), then bilinear sampling
# at the model's pixel centres, >= 0.5. Both are separable: model row v of a mask is a weighted sum
# of the source rows near its centre, whose weights are the tent's lerp of the discrete Gaussian
# (`_axis_weights`), and so are its columns. So a batch takes two batched matrix products: over the
# rows, chunk by chunk of CHUNK model rows and the source rows they reach (`_pass`; a blur of every
# source pixel would cost 6x more), then over the columns, alike on the transposed result or at once
# (`DENSE_MOST`).
CHUNK = 8  # model rows per product: fewer waste less of the source rows read, more run faster
GROUP = {"cpu": 8}  # samples framed together by device type: on a CPU what a group reads stays in its cache
DEVICE_GROUP = 64  # elsewhere (a GPU): few launches, bounded memory
# Model px up to which the columns' pass is one product over every source column, by device type;
# above it the columns go chunk by chunk like the rows. On a CPU (with one torch thread or two)
# the chunks win at every size, as OpenCV transposes the rows' result 14x faster than torch
# copies it (`_by_columns`; frame_masks 1-9% faster at 64 px, 22% at 128, BENCHMARKS.md).
# Elsewhere the single product up to 64 px stays, as it was chosen for a CPU (not measured on a GPU).
DENSE_MOST = {"cpu": 0}
DEVICE_DENSE_MOST = 64


def frame_masks(noisy: torch.Tensor, clean: torch.Tensor, framing: torch.Tensor, source: int,
                size: int, grey: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch's packed (B, ceil(source^2 / 8)) masks carried onto the model's `size` px input by
    their framings (B, 3: scale, x offset, y offset; `collate_framed`), both as `warp` carries a
    mask: (B, 1, size, size) float32 +1 / -1 each, or with `grey` each pixel's covered share
    mapped onto [-1, 1]. On the masks' device, in float32 whatever the autocast."""
    framing, batch = framing.to(noisy.device, torch.float64), noisy.shape[0]
    group = GROUP.get(noisy.device.type, DEVICE_GROUP)
    with torch.autocast(noisy.device.type, enabled=False):
        scale = framing[:, 0].repeat(2)  # both axes at once: y (rows), then x (columns)
        pixels, weights, reach = _axis_weights(torch.cat([framing[:, 2], framing[:, 1]]), scale, source, size)
        framed = torch.cat([_frame_group(noisy[at : at + group], clean[at : at + group], source,
                                         *_windows(pixels, weights, reach, at, min(group, batch - at), batch), grey)
                            for at in range(0, batch, group)])
    signed = torch.empty(2, batch, 1, size, size, device=noisy.device)  # x1 and x2, each contiguous
    signed.copy_(framed[:, :, None, :size, :size].transpose(0, 1)).mul_(2).sub_(1)
    return signed[0], signed[1]


def _windows(pixels: torch.Tensor, weights: torch.Tensor, reach: torch.Tensor, at: int, count: int,
             batch: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """`_axis_weights`' windows of `count` samples from `at`, along y and then along x (its second
    half), only as long as these samples reach."""
    length = int(reach[at : at + count].max())
    return tuple([part[first : first + count, ..., :length] for part in (pixels, weights)] for first in (at, batch + at))


def _frame_group(noisy: torch.Tensor, clean: torch.Tensor, source: int, rows: list[torch.Tensor],
                 cols: list[torch.Tensor], grey: bool) -> torch.Tensor:
    """`frame_masks` of a few samples, given `_axis_weights` along y (`rows`) and x (`cols`):
    (B, 2, C * CHUNK, C * CHUNK) bool, noisy then clean, or with `grey` their covered shares."""
    if source % 8 == 0:  # both masks' bytes row by row, unpacked at once: (B, source, 2 source)
        pair = unpack_bits(torch.cat([noisy.view(-1, source, source // 8), clean.view(-1, source, source // 8)], 2),
                           2 * source)
    else:
        pair = torch.cat([unpack_bits(m, source * source).view(-1, source, source) for m in (noisy, clean)], 2)
    batch, spread = pair.shape[0], rows[0].shape[1] * CHUNK  # model px in whole chunks, >= size
    across = _pass(pair, *rows)  # model y by (mask, source x)
    if spread <= DENSE_MOST.get(pair.device.type, DEVICE_DENSE_MOST):  # every source column the group reaches, at once
        low, high = (int(bound) for bound in torch.aminmax(cols[0]))
        framed = torch.bmm(across.view(batch, 2 * spread, source)[:, :, low : high + 1],
                           _dense(cols[0] - low, cols[1], high + 1 - low))
        return _levels(framed.view(batch, spread, 2, spread).transpose(1, 2), grey)
    # source x by (mask, model y): the image the columns' pass reads, both masks' chunks in one product
    framed = _pass(_by_columns(across, source), *cols).view(batch, spread, 2, spread)  # model x by (mask, model y)
    return _levels(framed.permute(0, 2, 3, 1), grey)


def _levels(coverage: torch.Tensor, grey: bool) -> torch.Tensor:
    """`cuboidtrain.fit.masks.levels` on the device: half covered or more, or the share itself."""
    return coverage.clamp(0.0, 1.0) if grey else coverage >= 0.5


def _by_columns(across: torch.Tensor, source: int) -> torch.Tensor:
    """The rows' pass (B, model y, (mask, source x)) -> (B, source x, (mask, model y)), contiguous.
    On a CPU by OpenCV's blocked transposes (each mask's into its columns), 14x faster than torch's
    copy of the permuted view, which any other device does."""
    batch, spread = across.shape[:2]
    if across.device.type != "cpu":
        return across.view(batch, spread, 2, source).permute(0, 3, 2, 1).reshape(batch, source, 2 * spread)
    image = across.new_empty(batch, source, 2 * spread)
    for rows, columns in zip(across.numpy(), image.numpy()):
        for mask in range(2):
            cv2.transpose(rows[:, mask * source : (mask + 1) * source], columns[:, mask * spread : (mask + 1) * spread])
    return image


def _dense(pixels: torch.Tensor, weights: torch.Tensor, source: int) -> torch.Tensor:
    """`_axis_weights`' chunks (B, C, L), (B, C, CHUNK, L) -> (B, source, C * CHUNK): each model
    px's weights over every source px, the right factor of one product."""
    batch, chunks = pixels.shape[:2]
    dense = torch.zeros(batch, chunks, CHUNK, source, device=weights.device)
    dense.scatter_add_(3, pixels[:, :, None, :].expand(-1, -1, CHUNK, -1), weights)
    return dense.view(batch, chunks * CHUNK, source).transpose(1, 2)


def _pass(image: torch.Tensor, pixels: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """One separable pass over (B, H, W) `image`: for each chunk of CHUNK model px, the weighted
    sums of the image rows `pixels` (B, C, L) by `weights` (B, C, CHUNK, L) -> (B, C * CHUNK, W)."""
    batch, height, width = image.shape
    chunks, reach = pixels.shape[1:]
    base = torch.arange(batch, device=image.device)[:, None, None] * height
    windows = image.reshape(batch * height, width).index_select(0, (pixels + base).view(-1))
    windows = windows.view(batch * chunks, reach, width).float()
    return torch.bmm(weights.reshape(batch * chunks, CHUNK, reach), windows).view(batch, chunks * CHUNK, width)


def _axis_weights(offset: torch.Tensor, scale: torch.Tensor, source: int,
                  size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Along one axis, per sample: for each chunk of CHUNK model px, the L source px it reaches
    (B, C, L) and their weights (B, C, CHUNK, L), the tent's lerp of the discrete Gaussian at
    each model px's centre in the source (`model = scale * source + offset`); and (B,) how many
    of the L each sample's chunks reach (the rest weigh 0)."""
    batch, chunks = offset.shape[0], -(-size // CHUNK)
    blur = torch.where(scale < 1, SHRINK_BLUR / scale, torch.zeros_like(scale))
    radius = torch.where(blur > 0, torch.round(blur * 8 + 1).long() | 1, torch.ones_like(blur, dtype=torch.long)) // 2
    needed = torch.ceil((CHUNK - 1) / scale).long() + 2 * radius + 2  # what the lerp of the taps reaches
    reach = int(needed.max())
    centre = (torch.arange(chunks * CHUNK, device=offset.device, dtype=torch.float64) - offset[:, None]) / scale[:, None]
    centre = centre.view(batch, chunks, CHUNK)  # source px
    first = centre[:, :, :1].floor() - radius[:, None, None]  # (B, C, 1): each chunk's first source px
    whole = (centre - first).floor()  # in [0, reach): the source px just below each centre, from `first`
    taps = _gaussian(blur, radius, reach)  # (B, 2 reach + 1): the Gaussian at -reach .. reach px
    # Source px first + l weighs taps(whole - l) (1 - frac) + taps(whole - l + 1) frac: a slice of
    # the (symmetric) taps, reversed, from reach - whole - 1.
    start = (reach - 1 - whole.long()).view(batch, -1)
    window = taps.unfold(1, reach + 1, 1)[torch.arange(batch, device=offset.device)[:, None], start]
    window = window.view(batch, chunks, CHUNK, reach + 1)
    weights = torch.lerp(window[..., 1:], window[..., :-1], (centre - first - whole).float()[..., None])
    pixels = first.long() + torch.arange(reach, device=offset.device)  # (B, C, L)
    inside = ((pixels >= 0) & (pixels < source)).to(weights.dtype)  # a source px off the image weighs 0
    return pixels.clamp(0, source - 1), weights.mul_(inside[:, :, None, :]), needed


def _gaussian(blur: torch.Tensor, radius: torch.Tensor, reach: int) -> torch.Tensor:
    """(B,) std in source px (0: none) and radius (cv2's for float images) -> (B, 2 reach + 1)
    float32: each sample's normalised discrete Gaussian at -reach .. reach px."""
    offsets, blur = torch.arange(-reach, reach + 1, device=blur.device, dtype=torch.float32), blur.float()[:, None]
    # the exponent clamped at -40 (exp(-8) at the radius): no exp underflows, 13x slower on a CPU;
    # beyond the radius the taps are 0 anyway
    taps = torch.where(blur > 0, torch.exp((-offsets**2 / (2 * blur.clamp(min=1e-6) ** 2)).clamp(min=-40.0)),
                       (offsets == 0).float())
    taps = taps * (offsets.abs() <= radius[:, None])
    return taps / taps.sum(1, keepdim=True)


