"""The soft-rasterised silhouette fit: the alternative optimiser, measured against
`cuboidtrain.geometry.mask_fit.fit_mask` (issue 20, Must have 3: choose the optimiser by measurement).

The same inputs, starts and parameter vector as `fit_mask` (`geometry`'s layout; the best
`starts` hypotheses of the same short lift of the networks' corners, `mask_fit.lift_starts`),
a different objective and solver:

* the model's silhouette drawn soft, SoftRas-style (Liu et al. 2019): a pixel's inside-ness of
  each convex part is sigmoid(-signed distance / sigma), the parts joined as 1 - prod(1 - p);
* compared with the mask pixel by pixel (`silhouette_loss`): a mask pixel the model leaves out
  costs its cross-entropy, linear in its depth outside the model (weight
  `MaskFitWeights.outside`); model over background costs less (`overhang`) and saturates, the
  more so the farther from the mask: occluders only remove pixels, as `fit_mask`'s robust rows
  tolerate; the Refiner's completion costs nothing, as there;
* plus `fit_mask`'s corner pull and ratio anchor;
* a blur schedule: sigma from a few px, where the loss sees far and is smooth, down to half a
  pixel; L-BFGS at a few blur levels, each start alone (or Adam, a blur level a step), on
  whitened parameters (`whitening`: a unit step moves the corners about one px), through
  torch's autograd. The projection is `geometry.project` written in torch (equal to 1e-9 px,
  tests/test_soft_mask_fit.py).

Measured against `fit_mask` from the same candidates (BENCHMARKS.md, "Choosing the mask-fit
optimiser"; benchmarks/accuracy/bench_optimizer.py, 100 masks a set): at 100 L-BFGS iterations a start,
more accurate on all 6 sets (mean corner error 3.93 -> 2.78 px clean box, 7.76 -> 6.76 `paper`
twobox; every median, hull median and depth/height median lower) but 35-40 times slower (413-522
against 11-15 ms, one thread): LM stays the default; `infer --optimizer soft` (FitOptions.optimizer)
fits with this one, for whom accuracy is worth half a second a shape class.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from cuboidtrain.geometry.camera_params import (SKEW_TABLE, CameraParams, CuboidFit, log_ratio_jacobian, object_basis, project,
                                      project_with_jacobian)
from cuboidtrain.geometry.mask_fit import STARTS, described, lift_starts
from cuboidtrain.geometry.outline import QUARTER_TURN, HullEdges, MaskFitWeights, MaskTarget, part_corners, hull_edges
from shared.shapes import Shape

DTYPE = torch.float64  # the projection's: it must equal numpy's to 1e-9 px
# The per-pixel work: half the memory traffic of float64, and px coordinates below 10^4 keep
# 1e-3 px; the pixels' costs are summed in float64.
RASTER_DTYPE = torch.float32
# An invalid hull slot's offset: far inside, so the max over a part's edges never takes it.
_NO_EDGE = -1e30


@dataclass(frozen=True)
class SoftSchedule:
    """How the soft fit walks: the blur from `sigma_start` to `sigma_end` px (geometric), the
    solver and its budget. The defaults are the best measured (BENCHMARKS.md)."""

    method: str = "lbfgs"  # one L-BFGS run per blur level and start; or "adam", one step per blur level
    iterations: int = 100  # L-BFGS iterations a start over all `stages`, or Adam steps
    stages: int = 3  # L-BFGS's blur levels
    sigma_start: float = 2.0
    sigma_end: float = 0.5
    step_per_sigma: float = 0.1  # Adam's learning rate per px of blur (whitened units: px of corner motion)
    silhouette: float = 1.0  # the silhouette term's weight against the corner pull and ratio anchor
    margin_px: float = 6.0  # the region of interest around the mask and the starts, beyond 3 sigma_start
    band_px: float = 4.0  # pixels this near the mask's outline are sampled one by one (SoftTarget)
    coarse_stride_sigma: float = 1.5  # the band is subsampled by floor(sigma / this) while the blur is wide

    def sigmas(self, count: int) -> np.ndarray:
        """`count` blur levels, geometric from sigma_start to sigma_end."""
        if count == 1:
            return np.array([self.sigma_end])
        return self.sigma_start * (self.sigma_end / self.sigma_start) ** (np.arange(count) / (count - 1))

    def stride(self, sigma: float) -> int:
        """The pixel grid's step at this blur: a sum over every other pixel is as good under a wide blur."""
        return max(1, int(sigma / self.coarse_stride_sigma))


# --- the projection, in torch ---------------------------------------------------------------


@lru_cache(maxsize=None)
def _torch_basis(shape: Shape) -> tuple[torch.Tensor, torch.Tensor]:
    """`geometry.object_basis` as tensors: coef (N 3, Q), const (N, 3)."""
    coef, const = object_basis(shape)
    n, q = len(const), coef.shape[2]
    return torch.tensor(coef.reshape(n * 3, q), dtype=DTYPE), torch.tensor(const, dtype=DTYPE)


def torch_object_points(params: torch.Tensor, shape: Shape, mirror: torch.Tensor) -> torch.Tensor:
    """`geometry.object_points`: (B, N, 3) labelled object corners; `mirror` (B,) bool reflects x."""
    coef, const = _torch_basis(shape)
    w, d = params[:, 0].exp(), params[:, 1].exp()
    theta = [w, d] if len(shape.parts) == 1 else [w, d, w / 2 - params[:, 11] * w, params[:, 12].exp()]
    points = (torch.stack(theta, dim=1) @ coef.T).reshape(len(params), -1, 3) + const
    sign = torch.ones(len(params), 1, 3, dtype=DTYPE)
    sign[:, 0, 0] = torch.where(mirror, -1.0, 1.0)
    return points * sign


def torch_rotation_matrices(rotvec: torch.Tensor) -> torch.Tensor:
    """`geometry.rotation_matrices` (Rodrigues), with gradients that stay finite at 0."""
    theta2 = (rotvec * rotvec).sum(1)
    small = theta2 < 1e-16
    theta = torch.where(small, 1.0, theta2).sqrt()  # sqrt's gradient at 0 is infinite: never taken there
    a = torch.where(small, 1.0 - theta2 / 6, theta.sin() / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - theta.cos()) / theta**2)
    k = (rotvec @ torch.as_tensor(SKEW_TABLE, dtype=DTYPE)).reshape(-1, 3, 3)
    return torch.eye(3, dtype=DTYPE) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def torch_project(params: torch.Tensor, shape: Shape, mirror: torch.Tensor) -> torch.Tensor:
    """`geometry.project` of (B, P) params: (B, N, 2) image points, differentiable."""
    rotated = torch_object_points(params, shape, mirror) @ torch_rotation_matrices(params[:, 2:5]).transpose(1, 2)
    depth = 1.0 + params[:, 8, None] * rotated[..., 2]
    xy = (rotated[..., :2] + params[:, None, 5:7]) * (params[:, 7].exp()[:, None, None] / depth[..., None])
    return xy + params[:, None, 9:11]


def torch_ratios(params: torch.Tensor, shape: Shape) -> torch.Tensor:
    """`geometry.ratios`: (B, 2 or 4) in `shape.ratio_names` order."""
    w, d = params[:, 0].exp(), params[:, 1].exp()
    if len(shape.parts) == 1:
        return torch.stack([d, w], dim=1)
    split, h_left = params[:, 11], params[:, 12].exp()
    return torch.stack([d, split * w, d / h_left, (1 - split) * w / h_left], dim=1)


# --- the soft silhouette --------------------------------------------------------------------


@dataclass(frozen=True)
class PixelGrid:
    """Where the soft silhouette is compared with the mask: sample points, the mask there, and
    the px each stands for."""

    points: torch.Tensor  # (R, 2) x, y px, RASTER_DTYPE
    inside: torch.Tensor  # (R,) 1.0 on the mask, 0.0 off it
    area: torch.Tensor  # (R,) px a sample stands for
    tolerance: torch.Tensor  # (R,) the weight of model over background there (`overhang_weights`)


class SoftTarget:
    """What the soft fit reads of a mask: its pixels in a region of interest (the mask's and the
    starts' bounding box with a margin: farther pixels are background under every hypothesis
    the fit visits), and the outline's size, which normalises the silhouette term as `fit_mask`
    normalises its rows.

    Only pixels near the mask's outline (|sdf| <= `band`) are sampled one by one (or on the
    blur's stride); the rest, where the mask is constant over a few px, one sample per
    COARSE x COARSE block, standing for the block's pixels off the band. A pixel far from both
    outlines costs and pulls nothing; one far from the mask's outline but misclassified by the
    model costs about its distance, a smooth function that a block's sample integrates well.
    4 to 5 times fewer samples on 256 px masks than the whole region. Background that the
    Refiner's completion covers (`completion.completed_target`: distance 0 off the mask) costs
    nothing under the model, as in `fit_mask`, and is not sampled."""

    COARSE = 4

    def __init__(self, target: MaskTarget, starts: np.ndarray, margin: float, band: float, robust_px: float):
        mask = target.mask.astype(bool)
        height, width = mask.shape
        ys, xs = np.nonzero(mask)
        low = np.minimum([xs.min(), ys.min()], starts.reshape(-1, 2).min(0)) - margin
        high = np.maximum([xs.max(), ys.max()], starts.reshape(-1, 2).max(0)) + margin
        x0, y0 = max(0, int(math.floor(low[0]))), max(0, int(math.floor(low[1])))
        x1, y1 = min(width, int(math.ceil(high[0])) + 1), min(height, int(math.ceil(high[1])) + 1)
        self.origin = np.array([x0, y0])
        self.mask, self.sdf = mask[y0:y1, x0:x1], target.sdf[y0:y1, x0:x1]
        counted = self.mask | (self.sdf > 0)  # not the completion's background
        self.near = counted & (np.abs(self.sdf) <= band)
        self.far = counted & ~self.near
        self.robust_px = robust_px
        self.norm = 1.0 / len(target.outline)  # fit_mask's norm squared
        self.blocks = self._blocks()
        self._grids: dict[int, PixelGrid] = {}

    def _blocks(self) -> tuple[np.ndarray, ...]:
        """The far pixels, one sample per block: its centre, the mask's value there (one value:
        a block's far pixels lie at least `band` px from the outline), their count and mean
        distance to the outline."""
        c = self.COARSE
        h, w = self.mask.shape
        pad = ((0, -h % c), (0, -w % c))

        def by_block(values: np.ndarray) -> np.ndarray:  # (h / c, w / c): the sum over each block's far pixels
            far = np.pad(self.far, pad)
            return (np.pad(values, pad) * far).reshape(far.shape[0] // c, c, -1, c).sum((1, 3))

        count = by_block(np.ones(self.mask.shape))
        by, bx = np.nonzero(count)
        centres = np.stack([bx * c, by * c], axis=1) + (c - 1) / 2  # the block's own centre (past a cut edge too)
        on_mask = by_block(self.mask.astype(np.float64)) * 2 > count
        distance = by_block(self.sdf) / np.maximum(count, 1)
        return centres, on_mask[by, bx], count[by, bx], distance[by, bx]

    def grid(self, stride: int) -> PixelGrid:
        """The band's pixels every `stride` px, and the far blocks (stride >= COARSE: every
        counted pixel of the region every `stride` px)."""
        if stride not in self._grids:
            ys, xs = np.mgrid[0 : self.mask.shape[0] : stride, 0 : self.mask.shape[1] : stride]
            keep = self.near[ys, xs] if stride < self.COARSE else (self.near | self.far)[ys, xs]
            ys, xs = ys[keep], xs[keep]
            points, inside, area, distance = (np.stack([xs, ys], axis=1), self.mask[ys, xs],
                                              np.full(len(ys), float(stride**2)), self.sdf[ys, xs])
            if stride < self.COARSE:
                centres, on_mask, count, block_distance = self.blocks
                points, inside = np.concatenate([points, centres]), np.concatenate([inside, on_mask])
                area, distance = np.concatenate([area, count]), np.concatenate([distance, block_distance])
            self._grids[stride] = PixelGrid(*(torch.tensor(v, dtype=RASTER_DTYPE) for v in (
                points + self.origin, inside, area, overhang_weights(distance, self.robust_px))))
        return self._grids[stride]


def overhang_weights(distance: np.ndarray, robust_px: float) -> np.ndarray:
    """The weight of model over a background pixel `distance` px from the mask: 1 near the
    outline, falling as 1 / (1 + (d / robust_px)^2) beyond it, so that the model's far overhang,
    maybe an occluded part (occluders only remove pixels), costs a bounded amount however wide."""
    return 1.0 / (1.0 + (np.maximum(distance, 0.0) / robust_px) ** 2)


@lru_cache(maxsize=None)
def unbiased_shift(outside: float, overhang: float) -> float:
    """Where an asymmetric cross-entropy puts a blurred straight edge, in units of sigma: its
    minimum lies u sigma outside the mask's edge, with overhang softplus(u) = outside softplus(-u)
    (0.47 for weights 1 and 0.5). The sigmoid is shifted by u so that the fitted outline itself
    sits on the mask's edge at every blur, not 0.47 sigma outside it."""
    low, high = -10.0, 10.0
    for _ in range(60):  # bisection: the difference grows monotonically in u
        u = 0.5 * (low + high)
        if overhang * math.log1p(math.exp(u)) > outside * math.log1p(math.exp(-u)):
            high = u
        else:
            low = u
    return 0.5 * (low + high)


def part_distances(image: torch.Tensor, shape: Shape, points: torch.Tensor) -> torch.Tensor:
    """(B, P, R) signed distance (positive outside) of pixel centres `points` (R, 2) to each
    convex part of silhouettes with corners `image` (B, N, 2): the largest outward offset over
    the part's hull edges (exact inside and across each edge; outside a vertex, a lower bound).
    Which corner pairs are hull edges is read off the detached corners (`outline.hull_edges`):
    a discrete choice, fixed within a step, as in `fit_mask`."""
    parts = part_corners(shape)
    hull = hull_edges(image.detach().numpy()[:, parts])  # fields (B, P, E, ...)
    used = max(1, int(hull.valid.sum(-1).max()))  # valid slots come first: the rest are never taken
    hull = HullEdges(*(v[..., :used, :] if v.ndim > 3 else v[..., :used] for v in
                       (hull.start, hull.direction, hull.normal, hull.valid, hull.pairs)))
    image = image.to(RASTER_DTYPE)
    ends = torch.as_tensor(parts[np.arange(len(parts))[:, None, None], hull.pairs])  # (B, P, E, 2) corner indices
    rows = torch.arange(len(image))[:, None, None]
    start, end = image[rows, ends[..., 0]], image[rows, ends[..., 1]]
    direction = end - start
    turned = torch.stack([direction[..., 1], -direction[..., 0]], dim=-1)  # outline.py's quarter turn
    # Outward, as hull_edges found it: the quarter turn's sign there.
    flip = np.sign(np.einsum("...d,...d->...", hull.normal, hull.direction @ QUARTER_TURN.T))
    normal = turned * torch.as_tensor(flip, dtype=RASTER_DTYPE)[..., None] / (turned.norm(dim=-1, keepdim=True) + 1e-12)
    valid = torch.as_tensor(hull.valid)[..., None]
    offsets = torch.where(valid, torch.einsum("rd,bped->bper", points, normal) - (start * normal).sum(-1)[..., None],
                          _NO_EDGE)
    return offsets.amax(dim=2)


def silhouette_loss(image: torch.Tensor, shape: Shape, grid: PixelGrid, sigma: float, weights: MaskFitWeights,
                    norm: float) -> torch.Tensor:
    """(B,) how badly the soft silhouettes explain the mask, times `norm`.

    A mask pixel costs sigma * -log p (the cross-entropy times the blur): about its depth
    outside the model, so a uniform miss of delta px (delta >> sigma) costs about delta^2 / 2
    per px of outline, the scale of `fit_mask`'s rows, whatever the blur. A background pixel
    costs its depth inside the model, sigma * -log(1 - p), likewise near the outline, but
    saturating past `robust_px` and weighted down with its distance from the mask
    (`overhang_weights`): model over background may be an occluded part, and a slab of it then
    costs a bounded amount, as `fit_mask`'s Cauchy-like rows tolerate it, not its area."""
    u = part_distances(image, shape, grid.points) / sigma - unbiased_shift(weights.outside, weights.overhang)
    log_out = torch.nn.functional.logsigmoid(u).sum(1)  # log(1 - p) of the union: prod of the parts' 1 - p
    miss, depth = -sigma * _log1mexp(log_out), -sigma * log_out  # -log p, -log(1 - p), in px
    overhang = depth * weights.robust_px / (depth + weights.robust_px)  # slope 1 at the outline, at most robust_px
    cost = weights.outside * grid.inside * miss + weights.overhang * grid.tolerance * (1 - grid.inside) * overhang
    return (cost * grid.area).to(DTYPE).sum(-1) * norm


def _log1mexp(x: torch.Tensor) -> torch.Tensor:
    """log(1 - exp(x)) for x <= 0, accurate at both ends (Maechler 2012)."""
    x = x.clamp(max=-torch.finfo(x.dtype).tiny)  # p = 0 to rounding (no part near the pixel): log p finite
    near = x > -math.log(2)
    # Each branch on inputs that are safe for it: torch.where's gradient multiplies the
    # branch not taken by 0, and 0 * inf is NaN.
    return torch.where(near, torch.log(-torch.expm1(torch.where(near, x, -1.0))),
                       torch.log1p(-torch.exp(torch.where(near, -1.0, x))))


# --- the fit ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SoftFitResult:
    """A soft fit and how it went: the record's CuboidFit, and the solver's work."""

    fit: CuboidFit
    evaluations: int  # loss and gradient evaluations (a batched call for several starts counts once)
    loss: float  # the chosen start's final loss at the last blur


def whitening(x0: np.ndarray, shape: Shape, mirrors: np.ndarray, anchor: np.ndarray | None,
              floor: float = 1e-6) -> np.ndarray:
    """(B, P, P) C with x = x0 + C z: the inverse square root of a Gauss-Newton matrix at x0,
    the corners' J^T J / (2N) (a unit step of z moves the corners by about one px rms) plus the
    ratio anchor's own (`anchor` (R,) its weights; None: no anchor). Adam's per-element steps
    and L-BFGS's first Hessian guess then act on corner motion, not on a mix of px, radians and
    logs with strongly correlated effects (tx and cx, s and k, width and yaw); the anchor's
    term keeps the directions the corners barely see (depth against focal length) at the
    anchor's scale. Eigenvalues are floored at `floor` of the largest: a bounded step."""
    _, jac = project_with_jacobian(x0, shape, mirrors)
    jac = jac.reshape(len(x0), -1, x0.shape[1])
    metric = jac.transpose(0, 2, 1) @ jac / jac.shape[1]
    if anchor is not None:
        weighted = anchor[None, :, None] * log_ratio_jacobian(x0, shape)
        metric = metric + weighted.transpose(0, 2, 1) @ weighted
    values, vectors = np.linalg.eigh(metric)
    values = np.maximum(values, floor * values[:, -1:])
    return (vectors / np.sqrt(values)[:, None, :]) @ vectors.transpose(0, 2, 1)


class _Objective:
    """The soft fit's loss of preconditioned params z (B, P): x = x0 + C z (`whitening`)."""

    def __init__(self, x0: np.ndarray, mirrors: np.ndarray, shape: Shape, soft: SoftTarget, corners: np.ndarray,
                 confidence: np.ndarray, prior_ratios: np.ndarray | None, weights: MaskFitWeights,
                 schedule: SoftSchedule):
        self.shape, self.soft, self.weights, self.schedule = shape, soft, weights, schedule
        self.mirrors = torch.as_tensor(mirrors, dtype=torch.bool)
        self.corners = torch.tensor(corners, dtype=DTYPE)
        self.pull = torch.tensor(weights.corners * np.sqrt(np.clip(confidence, 0.05, 1.0)), dtype=DTYPE)[None, :, None]
        self.prior = None if prior_ratios is None else torch.tensor(prior_ratios, dtype=DTYPE)
        self.anchor = torch.tensor(np.tile([weights.depth_ratio, weights.ratios], len(shape.parts)), dtype=DTYPE)
        self.evaluations = 0
        self.rebase(x0)

    def rebase(self, x0: np.ndarray) -> None:
        """z = 0 at params x0, whitened there."""
        self.x0 = torch.tensor(x0, dtype=DTYPE)
        anchor = None if self.prior is None else self.anchor.numpy()
        self.basis = torch.tensor(whitening(x0, self.shape, self.mirrors.numpy(), anchor), dtype=DTYPE)

    def params(self, z: torch.Tensor) -> torch.Tensor:
        return self.x0 + (self.basis @ z[..., None])[..., 0]

    def __call__(self, z: torch.Tensor, sigma: float) -> torch.Tensor:
        """(B,) losses: soft silhouette + corner pull + ratio anchor (the last two as in fit_mask)."""
        self.evaluations += 1
        x = self.params(z)
        image = torch_project(x, self.shape, self.mirrors)
        grid = self.soft.grid(self.schedule.stride(sigma))
        loss = self.schedule.silhouette * silhouette_loss(image, self.shape, grid, sigma, self.weights, self.soft.norm)
        loss = loss + 0.5 * self.soft.norm * (((image - self.corners) * self.pull) ** 2).sum((1, 2))
        if self.prior is not None:
            loss = loss + 0.5 * ((self.anchor * torch.log(torch_ratios(x, self.shape) / self.prior)) ** 2).sum(1)
        return loss


def fit_soft(mask: np.ndarray | MaskTarget, shape: Shape, corners: np.ndarray, confidence: np.ndarray,
             prior_ratios: np.ndarray | None = None, weights: MaskFitWeights = MaskFitWeights(), starts: int = STARTS,
             schedule: SoftSchedule = SoftSchedule()) -> SoftFitResult:
    """`fit_mask`'s drop-in by a soft-rasterised silhouette: the same inputs and starts, the same
    CuboidFit (`.fit`), found by gradient descent through a blur schedule (module notes)."""
    lifted = lift_starts(corners[None], confidence[None], shape)
    chosen = lifted.best(0, starts)
    x0, mirrors = lifted.params[chosen], lifted.mirrors[chosen]
    target = mask if isinstance(mask, MaskTarget) else MaskTarget.of(mask, weights)
    margin = schedule.margin_px + 3 * schedule.sigma_start
    soft = SoftTarget(target, np.concatenate([corners[None], project(x0, shape, mirrors)]), margin, schedule.band_px,
                      weights.robust_px)
    if schedule.method not in SOLVERS:
        raise ValueError(f"unknown soft-fit method {schedule.method!r}: {' or '.join(SOLVERS)}")
    # Adam's steps are per element: the starts go as one batch. L-BFGS's line search is one for
    # all it holds: each start alone, so that one start's step length is not the other's.
    groups = [np.arange(len(x0))] if schedule.method == "adam" else [np.array([row]) for row in range(len(x0))]
    params, final, evaluations = [], [], 0
    for rows in groups:
        objective = _Objective(x0[rows], mirrors[rows], shape, soft, corners, confidence, prior_ratios, weights,
                               schedule)
        z = torch.zeros_like(objective.x0, requires_grad=True)
        SOLVERS[schedule.method](objective, z, schedule)
        with torch.no_grad():
            final.append(torch.nan_to_num(objective(z, schedule.sigma_end), nan=math.inf).numpy())
            params.append(objective.params(z).numpy())
        evaluations += objective.evaluations
    final, x = np.concatenate(final), np.concatenate(params)
    best = int(np.argmin(final))
    camera = CameraParams(shape, x[best].copy(), bool(mirrors[best]))
    return SoftFitResult(described(target, shape, camera, weights), evaluations, float(final[best]))


def _adam(objective: _Objective, z: torch.Tensor, schedule: SoftSchedule) -> None:
    """Adam through the blur schedule, one blur level a step, its step shrinking with the blur;
    the starts as one batch (their losses summed: Adam's steps are per element)."""
    optimiser = torch.optim.Adam([z], lr=schedule.step_per_sigma * schedule.sigma_start)
    for sigma in schedule.sigmas(schedule.iterations):
        for group in optimiser.param_groups:
            group["lr"] = schedule.step_per_sigma * float(sigma)
        optimiser.zero_grad()
        _backward(objective, z, float(sigma))
        optimiser.step()


def _lbfgs(objective: _Objective, z: torch.Tensor, schedule: SoftSchedule) -> None:
    """L-BFGS (strong Wolfe line search) at each of `stages` blur levels, the iterations shared
    between them, each level whitened afresh where the last one ended (measured: that, and each
    start alone, took clean twobox medians from 2.8 to 0.5 px). The tolerances are tiny: the
    budget, not L-BFGS's own test, ends a level (its default stops on a flat stretch well short
    of the minimum)."""
    per_stage = max(1, schedule.iterations // schedule.stages)
    for sigma in schedule.sigmas(schedule.stages):
        with torch.no_grad():
            objective.rebase(objective.params(z).numpy())
            z.zero_()
        optimiser = torch.optim.LBFGS([z], lr=1.0, max_iter=per_stage, history_size=20, tolerance_grad=1e-10,
                                      tolerance_change=1e-12, line_search_fn="strong_wolfe")

        def closure(sigma=float(sigma)) -> torch.Tensor:
            optimiser.zero_grad()
            return _backward(objective, z, sigma)

        optimiser.step(closure)


def _backward(objective: _Objective, z: torch.Tensor, sigma: float) -> torch.Tensor:
    """The summed loss of the rows at this blur, its gradient left in z.grad. A row whose loss
    is not finite (a trial step past the camera) is left out: it pulls on no other."""
    loss = objective(z, sigma)
    total = loss[torch.isfinite(loss)].sum()
    total.backward()
    z.grad.nan_to_num_(0.0)
    return total


SOLVERS = {"adam": _adam, "lbfgs": _lbfgs}
