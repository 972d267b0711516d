"""The keypoint codec: keypoints -> heat maps for training, heat maps -> keypoints for a fit.

A codec pairs the two directions, as MMPose's keypoint codecs do: `encode` renders the
Estimator's training target x3, a Gaussian of std `sigma` px at each keypoint (B, N, 2) px,
and `decode` reads keypoints (B, N, 2) px and one score per keypoint back off heat maps
(B, N, H, W). Every codec encodes alike; they differ in how they decode, and `infer`,
`eval` and the report pick one by name from CODECS (`--extractor NAME`):

- `tabulator`: T's own output (the paper's method), passed through;
- `argmax`: each map's brightest pixel (whole pixels only);
- `centre-of-mass`: the mass of each map above half its maximum, whose centre
  is sub-pixel and ignores the faint background that would drag a plain mean
  towards the image centre;
- `dark`: DARK (Zhang et al., "Distribution-Aware Coordinate Representation for
  Human Pose Estimation", CVPR 2020): a Newton step on the log of the smoothed map
  at its argmax, exact for a Gaussian blob;
- `pdm`: the paper's section 4.1 alternative: argmax locations projected onto a
  Point Distribution Model (a PCA shape model, `cuboidtrain.models.pdm`), which makes
  the octet globally valid.

Every decoder takes `(heatmaps, tabulated)`, where `tabulated` is T's keypoints
for the same maps (T always runs: the ratios come from it alone, since a heat map
holds no 3D extent), and gives keypoints in the pixel-centre convention.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F

from cuboidtrain.models.pdm import PointDistributionModel
from cuboidtrain.models.settings import DEFAULT_PDM_COMPONENTS, EXTRACTORS, parse_components
from shared.checks import check_choice
from shared.errors import UsageError


def default_sigma(size: int) -> float:
    """Heat-map std in px when none is given: size/128, at least 1 (2 px at 256)."""
    return max(1.0, size / 128)


# ---- encoding ---------------------------------------------------------------------------


def render_heatmaps(keypoints: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """(B, N, 2) px -> (B, N, size, size): exp(-d^2 / 2 sigma^2), 1 at the keypoint.

    Pixel (row i, column j) has its centre at x = j, y = i (docs/contract.md, "Coordinates: pixel centres"), so the
    peak sits at the keypoint to sub-pixel accuracy. The Gaussian is separable:
    an outer product of a row and a column profile, cheap even at 256 px.
    """
    grid = torch.arange(size, device=keypoints.device, dtype=torch.float32)
    k = keypoints.float()
    gx = _profile(grid - k[..., 0:1], sigma)  # (B, N, W)
    gy = _profile(grid - k[..., 1:2], sigma)  # (B, N, H)
    return gy.unsqueeze(-1) * gx.unsqueeze(-2)


# A profile below exp(-TAIL) (8.9 sigma out) is 0. So no product of two profiles is a subnormal
# float, and no exp underflows: on a CPU either costs 10x (the whole path at 64 px, issue 29).
TAIL = 40.0


def _profile(offset: torch.Tensor, sigma: float) -> torch.Tensor:
    """exp(-offset^2 / 2 sigma^2), 0 beyond the TAIL."""
    exponent = -(offset**2) / (2 * sigma**2)
    return torch.where(exponent < -TAIL, 0.0, torch.exp(exponent.clamp(min=-TAIL)))  # out of place: differentiable


# ---- decoding: heat maps (B, N, H, W) -> keypoints (B, N, 2) px ------------------------------


def argmax(heatmaps: torch.Tensor, tabulated: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, H, W) -> (B, N, 2) px: the first brightest pixel's centre (x = column, y = row)."""
    width = heatmaps.shape[-1]
    index = heatmaps.flatten(2).argmax(-1)  # (B, N)
    return torch.stack([index % width, torch.div(index, width, rounding_mode="floor")], -1).float()


def centre_of_mass(heatmaps: torch.Tensor, tabulated: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, H, W) -> (B, N, 2) px: the centre of each map's mass above half its maximum.

    Subtracting the half-maximum (rather than cutting at it) keeps the weights
    continuous, so the estimate moves smoothly with the blob.
    """
    h, w = heatmaps.shape[-2:]
    maps = heatmaps.float()
    weights = (maps - 0.5 * maps.amax(dim=(-2, -1), keepdim=True)).clamp(min=0)
    mass = weights.sum(dim=(-2, -1))
    total = mass.clamp(min=1e-12)
    xs = torch.arange(w, dtype=maps.dtype, device=maps.device)
    ys = torch.arange(h, dtype=maps.dtype, device=maps.device)
    x = (weights.sum(-2) * xs).sum(-1) / total
    y = (weights.sum(-1) * ys).sum(-1) / total
    # An all-zero map has no mass at all: its argmax stands rather than a point at 0 / 0.
    # (A positive constant map is all mass: its centre is the image's.)
    return torch.where((mass > 0).unsqueeze(-1), torch.stack([x, y], -1), argmax(maps))


def gaussian_blur(maps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Each (H, W) map of (B, N, H, W) convolved with a normalised Gaussian (zero padding)."""
    radius = max(1, math.ceil(3 * sigma))
    taps = torch.arange(-radius, radius + 1, dtype=maps.dtype, device=maps.device)
    kernel = torch.exp(-(taps**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    b, n, h, w = maps.shape
    flat = maps.reshape(b * n, 1, h, w)
    flat = F.conv2d(flat, kernel.view(1, 1, 1, -1), padding=(0, radius))
    flat = F.conv2d(flat, kernel.view(1, 1, -1, 1), padding=(radius, 0))
    return flat.view(b, n, h, w)


def dark(heatmaps: torch.Tensor, tabulated: torch.Tensor | None = None, sigma: float = 1.0) -> torch.Tensor:
    """(B, N, H, W) -> (B, N, 2) px by DARK's Taylor expansion of the log heat map at its argmax.

    The map is smoothed with the training Gaussian (a network's maps are ragged;
    a Gaussian stays a Gaussian) and rescaled to its old maximum, then
    offset = -H^-1 g from the log map's gradient g and Hessian H, with DARK's own
    finite differences (steps of 1 for g and the mixed term, 2 for the pure second
    derivatives). Where H is not negative definite there is no peak to step to and
    the argmax stands; steps are capped at 1 px, which a true peak never needs.
    """
    maps = heatmaps.float()
    smooth = gaussian_blur(maps, sigma)
    smooth = smooth * (maps.amax(dim=(-2, -1), keepdim=True) / smooth.amax(dim=(-2, -1), keepdim=True).clamp(min=1e-12))
    logmap = smooth.clamp(min=1e-10).log()
    peak = argmax(smooth)  # (B, N, 2), the smoothed map's own peak
    b, n, h, w = logmap.shape
    padded = F.pad(logmap.reshape(b * n, 1, h, w), (2, 2, 2, 2), mode="replicate").view(b, n, h + 4, w + 4)
    px, py = peak[..., 0].long() + 2, peak[..., 1].long() + 2

    def at(dx: int, dy: int) -> torch.Tensor:  # log value at peak + (dx, dy), (B, N)
        flat_index = ((py + dy) * (w + 4) + (px + dx)).unsqueeze(-1)
        return padded.flatten(2).gather(-1, flat_index).squeeze(-1)

    centre = at(0, 0)
    gx, gy = 0.5 * (at(1, 0) - at(-1, 0)), 0.5 * (at(0, 1) - at(0, -1))
    hxx = 0.25 * (at(2, 0) - 2 * centre + at(-2, 0))
    hyy = 0.25 * (at(0, 2) - 2 * centre + at(0, -2))
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    det = hxx * hyy - hxy**2
    peaked = (hxx < 0) & (det > 1e-12)
    safe_det = torch.where(peaked, det, torch.ones_like(det))
    ox = -(hyy * gx - hxy * gy) / safe_det  # -H^-1 g, H = [[hxx, hxy], [hxy, hyy]]
    oy = -(hxx * gy - hxy * gx) / safe_det
    offset = torch.stack([ox, oy], -1).clamp(-1.0, 1.0)
    return peak + torch.where(peaked.unsqueeze(-1), offset, torch.zeros_like(offset))


def peak_scores(heatmaps: torch.Tensor) -> torch.Tensor:
    """(B, N, H, W) -> (B, N): each map's maximum, the Estimator's sigmoid confidence in its keypoint."""
    return heatmaps.float().flatten(2).amax(-1)


# ---- the codecs -------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Decoded:
    """What a codec reads off heat maps: keypoints and how sure the maps are of each."""

    keypoints: torch.Tensor  # (B, N, 2) px, pixel centres
    scores: torch.Tensor  # (B, N): each heat map's peak value, 0..1 for the Estimator's maps


class HeatmapCodec:
    """Keypoints <-> heat maps of `size` px at std `sigma` px. Subclasses say how to `locate`."""

    name: ClassVar[str]

    def __init__(self, size: int, sigma: float):
        self.size, self.sigma = size, sigma

    @classmethod
    def for_model(cls, model, pdm_components: str | int | float = DEFAULT_PDM_COMPONENTS) -> "HeatmapCodec":
        """The codec of `model` (a CuboidNet: its size and the sigma S was trained to draw)."""
        return cls(model.size, model.sigma)

    def encode(self, keypoints: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) px -> (B, N, size, size) heat maps: the Estimator's training target."""
        return render_heatmaps(keypoints, self.size, self.sigma)

    def decode(self, heatmaps: torch.Tensor, tabulated: torch.Tensor | None = None) -> Decoded:
        """(B, N, H, W) heat maps and T's keypoints for them -> keypoints and per-keypoint scores."""
        return Decoded(self.locate(heatmaps, tabulated), peak_scores(heatmaps))

    def locate(self, heatmaps: torch.Tensor, tabulated: torch.Tensor | None) -> torch.Tensor:
        raise NotImplementedError


class TabulatorCodec(HeatmapCodec):
    name = "tabulator"

    def locate(self, heatmaps, tabulated):
        return tabulated


class ArgmaxCodec(HeatmapCodec):
    name = "argmax"

    def locate(self, heatmaps, tabulated):
        return argmax(heatmaps)


class CentreOfMassCodec(HeatmapCodec):
    name = "centre-of-mass"

    def locate(self, heatmaps, tabulated):
        return centre_of_mass(heatmaps)


class DarkCodec(HeatmapCodec):
    name = "dark"

    def locate(self, heatmaps, tabulated):
        return dark(heatmaps, sigma=self.sigma)  # smoothed with the Gaussian S was trained to draw


class PdmCodec(HeatmapCodec):
    """Argmax locations made globally valid by a Point Distribution Model (paper, Figure 5)."""

    name = "pdm"

    def __init__(self, size: int, sigma: float, pdm: PointDistributionModel, components: int | float):
        super().__init__(size, sigma)
        self.pdm, self.components = pdm, components
        self.active = pdm.active_components(components)  # checks the value early, with a clear error

    @classmethod
    def for_model(cls, model, pdm_components: str | int | float = DEFAULT_PDM_COMPONENTS) -> "PdmCodec":
        """`pdm_components` is a count of active components (an integer >= 1) or the fraction of
        shape variance to keep (in (0, 1)); the PDM is the one saved in the model file
        (`model.pdm`), fitted on the keypoints it was trained on."""
        if getattr(model, "pdm", None) is None:
            raise UsageError(f"--extractor pdm: this {model.shape} model carries no point distribution model; "
                             f"pack it with `cuboidtrain models pack --pdm-spool SPOOL` (the spool it trained on)")
        return cls(model.size, model.sigma, model.pdm, parse_components(pdm_components))

    def locate(self, heatmaps, tabulated):
        projected = self.pdm.project(argmax(heatmaps).cpu().double().numpy(), self.components)
        return torch.from_numpy(projected).to(device=heatmaps.device, dtype=torch.float32)


# Name -> codec class; the names are settings.EXTRACTORS (which the command line offers without torch).
CODECS: dict[str, type[HeatmapCodec]] = {
    codec.name: codec for codec in (TabulatorCodec, ArgmaxCodec, CentreOfMassCodec, DarkCodec, PdmCodec)}


def make_codec(name: str, model, pdm_components: str | int | float = DEFAULT_PDM_COMPONENTS) -> HeatmapCodec:
    """The codec `name` (`--extractor`) for `model`; an unknown name is a UsageError naming the choices."""
    return CODECS[check_choice("--extractor", name, EXTRACTORS)].for_model(model, pdm_components)
