"""The `compact` architecture: R, S and T built for accuracy per CPU-second.

Same roles and legible outputs as the paper's networks (`cuboidtrain.models.networks`):

Refiner (R): mask (B, 1, H, W) -> clean mask (B, 1, H, W), tanh.
Estimator (S): mask (B, 1, H, W) -> one Gaussian heat map per corner (B, N, H, W), sigmoid.
Tabulator (T): heat maps (B, N, H, W) -> keypoints (B, N, 2) px and ratios (B, R).

What makes it cheap:

* Plain 3x3 convolutions at a fraction of ResNet-18's width (on a CPU they
  train faster than depthwise ones of the same accuracy), with the work done at
  stride 2 and below. Only R has a full-resolution stage (8 channels, on the
  input itself), so its edges stay pixel-sharp.
* S's maps are computed at stride 2 and upsampled: a Gaussian of std 2 px is
  smooth enough for that to lose nothing.
* T is fully convolutional (CoordConv input, U-Net context) and ends in one
  spatial softmax per corner whose expectation is the keypoint (integral
  regression / DSNT). Its coordinates stay spatial and differentiable, so it
  trains in a fraction of the steps a pooled-then-linear readout needs, and it
  still sees every map before it places any corner: an occluded corner is placed
  from the others. Its logits start from S's own maps (a learned gain), so a
  sharp map already gives its peak; the convolutions learn the corrections.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

WIDTHS = (24, 48, 96, 128)  # channels at strides 2, 4, 8, 16
SLIM_WIDTHS = (16, 32, 64, 128)  # the `slim` arch's: for inputs of twice the side (128 px)
FULL_WIDTH = 8  # channels of the full-resolution stage


def conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def upsample_to(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


class CompactUNet(nn.Module):
    """(B, cin, H, W) -> features (B, widths[0], H/2, W/2) and the deepest ones (B, widths[-1], H/16, W/16).

    Encoder: a stride-2 stem, then one strided and one plain conv per level.
    Decoder: upsample, concatenate the level's skip, one conv, back to stride 2.
    """

    def __init__(self, in_channels: int, widths: tuple[int, ...] = WIDTHS):
        super().__init__()
        self.stem = nn.Sequential(conv_bn_relu(in_channels, widths[0], stride=2), conv_bn_relu(widths[0], widths[0]))
        self.down = nn.ModuleList(
            nn.Sequential(conv_bn_relu(cin, cout, stride=2), conv_bn_relu(cout, cout))
            for cin, cout in zip(widths[:-1], widths[1:])
        )
        self.up = nn.ModuleList(
            conv_bn_relu(deep + skip, skip) for deep, skip in zip(widths[:0:-1], widths[-2::-1])
        )

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        skips = [self.stem(x)]
        for level in self.down:
            skips.append(level(skips[-1]))
        deepest = y = skips.pop()
        for block in self.up:
            skip = skips.pop()
            y = block(torch.cat([upsample_to(y, skip), skip], dim=1))
        return y, deepest


class FullResolutionHead(nn.Module):
    """Stride-2 features and the full-resolution input -> `out_channels` full-resolution logits."""

    def __init__(self, in_channels: int, features: int, out_channels: int):
        super().__init__()
        self.reduce = nn.Conv2d(features, FULL_WIDTH, 1)
        self.fine = conv_bn_relu(FULL_WIDTH + in_channels, FULL_WIDTH)
        self.head = nn.Conv2d(FULL_WIDTH, out_channels, 1)

    def forward(self, features: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        coarse = upsample_to(self.reduce(features), x)
        return self.head(self.fine(torch.cat([coarse, x], dim=1)))


class CompactRefiner(nn.Module):
    """Noisy, occluded mask -> clean mask, both +1 object / -1 background."""

    def __init__(self, widths: tuple[int, ...] = WIDTHS):
        super().__init__()
        self.body = CompactUNet(1, widths)
        self.head = FullResolutionHead(1, widths[0], 1)

    def forward(self, mask: torch.Tensor) -> torch.Tensor:
        features, _ = self.body(mask)
        return torch.tanh(self.head(features, mask))


class CompactEstimator(nn.Module):
    """Mask -> one heat map per keypoint, each in (0, 1), computed at stride 2 and upsampled."""

    def __init__(self, num_keypoints: int, widths: tuple[int, ...] = WIDTHS):
        super().__init__()
        self.body = CompactUNet(1, widths)
        self.head = nn.Conv2d(widths[0], num_keypoints, 1)
        nn.init.constant_(self.head.bias, -2.19)  # maps start near 0, as the paper arch's (CenterNet's prior)

    def forward(self, mask: torch.Tensor) -> torch.Tensor:
        features, _ = self.body(mask)
        return torch.sigmoid(upsample_to(self.head(features), mask))


class CompactTabulator(nn.Module):
    """Heat maps -> keypoints (px, pixel-centre convention) by per-corner spatial expectation, and ratios.

    The maps, joined by x/y coordinate channels, go through a U-Net whose stride-2
    features give one logit map per corner: gain * log(map) + correction, the map
    pooled to stride 2 (a Gaussian of std >= 1 px keeps its centroid under 2x2
    averaging). A softmax over each logit map is a distribution over the stride-2
    cell centres; its mean is the keypoint, sub-pixel and differentiable.

    The grid reaches `border` px beyond each side of the image (the maps are
    padded with zeros, the coordinate ramps continue): a corner hidden below the
    visible silhouette's frame, a building's bottom behind a parked car, can be
    placed where it is instead of clipped to the edge. The ratios come from the
    pooled deepest features. The readout runs in float32.
    """

    def __init__(self, num_keypoints: int, num_ratios: int, size: int, widths: tuple[int, ...] = WIDTHS):
        super().__init__()
        self.num_keypoints, self.num_ratios, self.size = num_keypoints, num_ratios, size
        self.body = CompactUNet(num_keypoints + 2, widths)
        self.correction = nn.Conv2d(widths[0], num_keypoints, 1)
        # Near zero, not zero: T starts by reading its maps (below), and every layer still gets a gradient.
        nn.init.normal_(self.correction.weight, std=1e-3)
        nn.init.zeros_(self.correction.bias)
        # softmax(gain * log map) is map ** gain, normalised: at gain 1 a true map's own Gaussian,
        # whose mean is its centre to ~0.01 px; 2 starts sharper, so that a background of faint
        # values (a sigmoid's never reach 0) weighs less. A gain on the map itself would
        # sharpen it into an argmax on the stride-2 grid (0.5 px off).
        self.gain = nn.Parameter(torch.tensor(2.0))
        self.ratio_head = nn.Linear(widths[-1], num_ratios)
        self.border = 2 * (size // 16)  # px, even: padded pixels pair up under the 2x2 pooling
        padded = size + 2 * self.border
        # Cell j of the stride-2 grid averages padded pixels 2j, 2j + 1, which are image pixels
        # 2j - border and 2j + 1 - border: its centre is x = 2j + 0.5 - border.
        centres = torch.arange(padded // 2, dtype=torch.float32) * 2 + 0.5 - self.border
        self.register_buffer("centres", centres, persistent=False)
        ramp = (torch.arange(padded, dtype=torch.float32) - self.border) / (size - 1) * 2 - 1  # -1..1 on the image
        self.register_buffer("coords", torch.stack(torch.meshgrid(ramp, ramp, indexing="xy")), persistent=False)

    def keypoint_range(self) -> tuple[float, float]:
        """The least and greatest coordinate (px) it can output: the outermost cell centres."""
        return self.centres[0].item(), self.centres[-1].item()

    def forward(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n = heatmaps.shape[:2]
        padded = F.pad(heatmaps, (self.border,) * 4)  # (B, N, P, P), P = S + 2 border
        coords = self.coords.to(heatmaps.dtype).expand(b, -1, -1, -1)
        features, deepest = self.body(torch.cat([padded, coords], dim=1))  # (B, C, P/2, P/2)
        pooled = F.avg_pool2d(padded, 2)  # (B, N, P/2, P/2), on the features' grid
        with torch.autocast(device_type=heatmaps.device.type, enabled=False):
            log_map = torch.log(pooled.float().clamp(min=1e-6))
            logits = self.gain * log_map + self.correction(features.float())  # (B, N, P/2, P/2)
            weights = torch.softmax(logits.flatten(2), dim=-1).view_as(logits)
            x = (weights.sum(dim=2) * self.centres).sum(dim=-1)  # marginal over rows, then E[x]
            y = (weights.sum(dim=3) * self.centres).sum(dim=-1)
            keypoints = torch.stack([x, y], dim=-1)  # full-res pixel centres (see `centres`)
            ratios = F.softplus(self.ratio_head(deepest.float().mean(dim=(2, 3))))
        return keypoints, ratios
