"""Targets rendered on the training device: heat maps from keypoints, masks from packed bits.

The spool stores neither float masks nor heat maps (8x and ~1000x larger); the
trainer ships packed bits and keypoints to its device and renders the paper's
(x1, x2, x3, x4) there, per batch.
"""
from __future__ import annotations

import torch

_BIT_SHIFTS = torch.arange(7, -1, -1, dtype=torch.uint8)  # np.packbits is big-endian within a byte


def render_heatmaps(keypoints: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """(B, N, 2) px -> (B, N, size, size): exp(-d^2 / 2 sigma^2), 1 at the keypoint.

    Pixel (row i, column j) has its centre at x = j, y = i (docs/contract.md, "Coordinates: pixel centres"), so the
    peak sits at the keypoint to sub-pixel accuracy. The Gaussian is separable:
    an outer product of a row and a column profile, cheap even at 256 px.
    """
    grid = torch.arange(size, device=keypoints.device, dtype=torch.float32)
    k = keypoints.float()
    gx = torch.exp(-((grid - k[..., 0:1]) ** 2) / (2 * sigma**2))  # (B, N, W)
    gy = torch.exp(-((grid - k[..., 1:2]) ** 2) / (2 * sigma**2))  # (B, N, H)
    return gy.unsqueeze(-1) * gx.unsqueeze(-2)


def unpack_masks(packed: torch.Tensor, size: int) -> torch.Tensor:
    """(B, size*size/8) uint8 packed bits -> (B, 1, size, size) float32, +1 object / -1 background."""
    bits = (packed.unsqueeze(-1) >> _BIT_SHIFTS.to(packed.device)) & 1  # (B, bytes, 8)
    bits = bits.reshape(packed.shape[0], -1)[:, : size * size]
    return bits.view(-1, 1, size, size).float() * 2 - 1


def prepare_batch(batch: dict, device: torch.device, sigma: float, size: int) -> dict[str, torch.Tensor]:
    """A loader batch -> the paper's x1 (noisy), x2 (clean), x3 (heat maps), x4 (keypoints), ratios."""
    non_blocking = device.type == "cuda"
    keypoints = batch["keypoints"].to(device, non_blocking=non_blocking)
    return {
        "x1": unpack_masks(batch["noisy"].to(device, non_blocking=non_blocking), size),
        "x2": unpack_masks(batch["clean"].to(device, non_blocking=non_blocking), size),
        "x3": render_heatmaps(keypoints, size, sigma),
        "x4": keypoints,
        "ratios": batch["ratios"].to(device, non_blocking=non_blocking),
    }
