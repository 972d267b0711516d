"""The three networks of paper 3.2, the registry of architectures that build them, and CuboidNet, which chains them.

`paper` is the paper's: all three on torchvision's ResNet-18 (below). `compact`
(cuboidtrain.models.compact) keeps the roles and outputs at a fraction of the cost.

Refiner (R): FCN, mask (B, 1, H, W) -> refined mask (B, 1, H, W), tanh.
Estimator (S): FCN, mask (B, 1, H, W) -> heat maps (B, N, H, W), sigmoid.
Tabulator (T): CNN, heat maps (B, N, H, W) -> keypoints (B, N, 2) in px and ratios (B, R).

`CuboidNet.forward` is the chain T(S(R^K(mask))), written once: training, eval,
infer and the ONNX export all run it, and it returns a `ChainOutput`.

The FCNs are U-Nets: the ResNet-18 encoder runs at strides 2..32 and a decoder
climbs back with a skip connection at every stride, down to a full-resolution
branch on the input itself. Without that last skip a peak could only be placed
to within the stride of the coarsest feature it came from; with it the
heat maps are sharp at the pixel, which the sub-pixel target needs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from cuboidtrain.models.codec import default_sigma
from cuboidtrain.models import compact
from cuboidtrain.models.refine import refine
from shared.errors import UsageError
from shared.shapes import get_shape

DECODER_WIDTHS = (256, 128, 64, 32, 16)  # channels at strides 16, 8, 4, 2, 1


def resnet18_backbone(in_channels: int) -> nn.Module:
    """torchvision's ResNet-18, untrained, its stem taking `in_channels` channels."""
    # Imported here, not at the top: torchvision's import pulls in torch._dynamo (2-3 s on this
    # CPU), and only the `paper` arch needs it; `infer` with the shipped compact models does not.
    from torchvision.models import resnet18

    net = resnet18(weights=None)
    net.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
    return net


def conv_block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )


class UNetResNet18(nn.Module):
    """ResNet-18 encoder, skip-connected decoder, 1x1 head: (B, cin, H, W) -> (B, cout, H, W) logits."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        r = resnet18_backbone(in_channels)
        self.stem = nn.Sequential(r.conv1, r.bn1, r.relu)  # stride 2, 64 ch
        self.pool = r.maxpool
        self.layers = nn.ModuleList([r.layer1, r.layer2, r.layer3, r.layer4])  # strides 4, 8, 16, 32
        self.full = conv_block(in_channels, DECODER_WIDTHS[-1])  # stride 1: the input's own detail
        skips = (256, 128, 64, 64, DECODER_WIDTHS[-1])  # channels of what joins at strides 16, 8, 4, 2, 1
        cin = 512
        self.up = nn.ModuleList()
        for skip, width in zip(skips, DECODER_WIDTHS):
            self.up.append(conv_block(cin + skip, width))
            cin = width
        self.head = nn.Conv2d(cin, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        full = self.full(x)
        s2 = self.stem(x)
        features = [self.pool(s2)]
        for layer in self.layers:
            features.append(layer(features[-1]))
        s4, s8, s16, s32 = features[1:]
        y = s32
        for block, skip in zip(self.up, (s16, s8, s4, s2, full)):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = block(torch.cat([y, skip], dim=1))
        return self.head(y)


class Refiner(nn.Module):
    """Noisy, occluded mask -> clean mask, both +1 object / -1 background."""

    def __init__(self):
        super().__init__()
        self.net = UNetResNet18(1, 1)

    def forward(self, mask: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(mask))


class Estimator(nn.Module):
    """Mask -> one heat map per keypoint, each in (0, 1)."""

    def __init__(self, num_keypoints: int):
        super().__init__()
        self.net = UNetResNet18(1, num_keypoints)
        # Start the maps near 0, not 0.5 (CenterNet's prior, sigmoid(-2.19) = 0.1): a heat
        # map is almost all background, and from 0.5 the first thousand steps only learn that.
        nn.init.constant_(self.net.head.bias, -2.19)

    def forward(self, mask: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(mask))


class Tabulator(nn.Module):
    """Heat maps -> keypoints (px, pixel-centre convention) and the shape's ratios.

    Two coordinate channels (x and y in [-1, 1], CoordConv) join the heat maps:
    a pooled CNN must otherwise infer position from padding effects alone.
    Coordinates are sigmoid * size - 0.5, which spans the image edge to edge
    when integers are pixel centres. The head runs in float32 even under
    autocast: a float16 256 has a step of 0.25 px, a bfloat16 one of 2 px.
    """

    def __init__(self, num_keypoints: int, num_ratios: int, size: int):
        super().__init__()
        self.num_keypoints, self.num_ratios, self.size = num_keypoints, num_ratios, size
        net = resnet18_backbone(num_keypoints + 2)
        self.features = nn.Sequential(*list(net.children())[:-1])  # everything up to the pooled 512 vector
        self.fc = nn.Linear(512, num_keypoints * 2 + num_ratios)
        ramp = torch.linspace(-1.0, 1.0, size)
        self.register_buffer("coords", torch.stack(torch.meshgrid(ramp, ramp, indexing="xy")), persistent=False)

    def keypoint_range(self) -> tuple[float, float]:
        """The least and greatest coordinate (px) it can output: the image, edge to edge."""
        return -0.5, self.size - 0.5

    def forward(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = heatmaps.shape[0]
        coords = self.coords.to(heatmaps.dtype).expand(b, -1, -1, -1)
        pooled = self.features(torch.cat([heatmaps, coords], dim=1)).flatten(1)  # (B, 512)
        with torch.autocast(device_type=pooled.device.type, enabled=False):
            out = self.fc(pooled.float())
        n = self.num_keypoints
        keypoints = torch.sigmoid(out[:, : 2 * n]).view(b, n, 2) * self.size - 0.5
        ratios = F.softplus(out[:, 2 * n :])  # ratios of extents are positive
        return keypoints, ratios


# The registry (timm's pattern): an architecture's name -> a constructor of its (R, S, T)
# from (num_keypoints, num_ratios, size). The name is stored in every config and checkpoint.
Parts = tuple[nn.Module, nn.Module, nn.Module]
ARCHS: dict[str, Callable[[int, int, int], Parts]] = {}
DEFAULT_ARCH = "compact"


def register_arch(name: str):
    def register(constructor: Callable[[int, int, int], Parts]):
        ARCHS[name] = constructor
        return constructor
    return register


def check_arch(name: str) -> str:
    if name not in ARCHS:
        raise UsageError(f"arch {name!r}: expected one of {', '.join(ARCHS)}")
    return name


@register_arch("paper")
def paper_parts(num_keypoints: int, num_ratios: int, size: int) -> Parts:
    """The paper's networks (three ResNet-18s, 28 GFLOP at 256 px): Table 3 is reproduced with these."""
    return Refiner(), Estimator(num_keypoints), Tabulator(num_keypoints, num_ratios, size)


@register_arch("compact")
def compact_parts(num_keypoints: int, num_ratios: int, size: int) -> Parts:
    """Narrow U-Nets at stride 2 and a spatial-expectation T (cuboidtrain.models.compact): the shipped models."""
    return _compact(num_keypoints, num_ratios, size, compact.WIDTHS)


@register_arch("slim")
def slim_parts(num_keypoints: int, num_ratios: int, size: int) -> Parts:
    """The compact design narrower (16, 32, 64, 128 channels): a 128 px input, twice the side of
    the shipped 64 px, at 1.6x their networks' CPU time through infer where compact would take 2.2x
    (BENCHMARKS.md, "The campaign's model": it learns more slowly per sample than compact at 128 px)."""
    return _compact(num_keypoints, num_ratios, size, compact.SLIM_WIDTHS)


@register_arch("tiny")
def tiny_parts(num_keypoints: int, num_ratios: int, size: int) -> Parts:
    """The compact design at a few channels: for tests and smoke runs, not for fitting."""
    return _compact(num_keypoints, num_ratios, size, (4, 8, 8, 8))


def _compact(num_keypoints: int, num_ratios: int, size: int, widths: tuple[int, ...]) -> Parts:
    return (compact.CompactRefiner(widths), compact.CompactEstimator(num_keypoints, widths),
            compact.CompactTabulator(num_keypoints, num_ratios, size, widths))


@dataclass(frozen=True, eq=False)  # eq=False: tensors have no single truth value
class ChainOutput:
    """What the chain T(S(R^K(mask))) gives for a (B, 1, S, S) batch, with grads where they flowed."""

    refined: torch.Tensor  # (B, 1, S, S) R's tanh output after K passes (the mask itself when K = 0)
    heatmaps: torch.Tensor  # (B, N, S, S) S's maps, in (0, 1)
    keypoints: torch.Tensor  # (B, N, 2) px: T's, or whatever read them off the heat maps (Fitter.predict)
    tabulated: torch.Tensor  # (B, N, 2) px: T's own, whatever reads `keypoints`
    ratios: torch.Tensor  # (B, R) T's
    refine_steps: int  # Refiner passes run: the most any mask of the batch took
    refine_converged: bool  # every mask settled (always True for a fixed K)


class CuboidNet(nn.Module):
    """R, S and T for one shape class at one size; `forward` chains them (training phase 2 on,
    eval, infer, export)."""

    def __init__(self, shape: str, size: int, sigma: float | None = None, arch: str = DEFAULT_ARCH,
                 grey_input: bool = False):
        super().__init__()
        geometry = get_shape(shape)
        self.shape, self.size, self.arch = shape, size, check_arch(arch)
        # Whether R reads a grey input (each pixel's covered share, `cuboidtrain.fit.masks.levels`) or a
        # binary one: trained on one, a model is shown that one (its checkpoint keeps which).
        self.grey_input = grey_input
        # The heat maps' Gaussian std in px that S was trained to draw: sub-pixel decoders need it.
        self.sigma = sigma if sigma is not None else default_sigma(size)
        # The shape model of --extractor pdm (cuboidtrain.models.pdm), saved in a model file; None until one is set.
        self.pdm = None
        self.refiner, self.estimator, self.tabulator = ARCHS[arch](
            geometry.num_keypoints, len(geometry.ratio_names), size)

    def forward(self, mask: torch.Tensor, refine_steps: int | None = 1) -> ChainOutput:
        """T(S(R^K(mask))) (paper 3.4) on a (B, 1, S, S) batch in [-1, 1] (+-1, or grey for a
        `grey_input` model), K = `refine_steps` passes of R, the first on the mask as given, each
        later one on the sign of the last (None: until settled, `cuboidtrain.models.refine`).
        One pass is what training chains: the sign of a +-1 mask is that mask, value for value."""
        refined, steps_run, converged = refine(self.refiner, mask, refine_steps)
        heatmaps = self.estimator(refined)  # S sees R's tanh output, not its sign, as in training's chained phases
        keypoints, ratios = self.tabulator(heatmaps)
        return ChainOutput(refined=refined, heatmaps=heatmaps, keypoints=keypoints, tabulated=keypoints,
                           ratios=ratios, refine_steps=steps_run, refine_converged=converged)


def build_model(shape: str, size: int, seed: int = 0, sigma: float | None = None,
                arch: str = DEFAULT_ARCH, grey_input: bool = False) -> CuboidNet:
    """A freshly initialised model; the same seed gives the same weights."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return CuboidNet(shape, size, sigma, arch, grey_input)
