"""A LoaderBatch on the training device as the paper names the chain's inputs and targets (3.3.2):
x1 (noisy), x2 (clean), x3 (heat maps, rendered here), x4 (keypoints), ratios.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from cuboidtrain.data.device_framing import frame_masks, unpack_masks
from cuboidtrain.data.loader import LoaderBatch
from cuboidtrain.models.codec import render_heatmaps


@dataclass(frozen=True)
class ChainBatch:
    """One batch as the paper names the chain's inputs and targets (3.3.2), on the training device."""

    x1: torch.Tensor  # (B, 1, S, S) +-1: the noisy, occluded mask, R's input
    x2: torch.Tensor  # (B, 1, S, S) +-1: the clean mask, R's target and S's input in phase 1
    x3: torch.Tensor  # (B, N, S, S): the keypoints' heat maps, S's target and T's input in phase 1
    x4: torch.Tensor  # (B, N, 2) px: the keypoints, T's target
    ratios: torch.Tensor  # (B, R): the shape's ratios, T's other target


def prepare_batch(batch: LoaderBatch, device: torch.device, sigma: float, size: int, grey: bool = False) -> ChainBatch:
    """A loader batch -> the paper's x1, x2, x3, x4 and ratios on `device`; a batch with framings
    framed at `size` on the device (`frame_masks`; with `grey` both masks as each pixel's covered
    share, as a grey-input model is shown them), one without unpacked there (binary: its own pixels)."""
    non_blocking = device.type == "cuda"
    keypoints = batch.keypoints.to(device, non_blocking=non_blocking)
    noisy = batch.noisy.to(device, non_blocking=non_blocking)
    clean = batch.clean.to(device, non_blocking=non_blocking)
    if batch.framing is not None:
        x1, x2 = frame_masks(noisy, clean, batch.framing, batch.source, size, grey)
    elif grey:
        raise ValueError("a grey input needs the batch's framings (a reframing loader): a spool's own masks are binary")
    else:
        x1, x2 = unpack_masks(noisy, size), unpack_masks(clean, size)
    return ChainBatch(
        x1=x1,
        x2=x2,
        x3=render_heatmaps(keypoints, size, sigma),
        x4=keypoints,
        ratios=batch.ratios.to(device, non_blocking=non_blocking),
    )
