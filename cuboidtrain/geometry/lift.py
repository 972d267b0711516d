"""Lift: named image corners -> the camera and cuboid that project onto them
(`cuboidtrain.geometry.camera_params`'s parameters), and the batched Levenberg-Marquardt solver
that the lift and the mask fit (`cuboidtrain.geometry.outline`) share.

Starts: the algebraic one from the box's vanishing points (`cuboidtrain.geometry.vanishing`:
exact for perspective views), and the weak-perspective (affine) lift, both depth orders
(Necker), times a few perspective strengths k (exact for distant ones); then LM on the
reprojection error with the projection's analytic Jacobian. Measured on exact generated
corners (benchmarks/accuracy/bench_lift.py, tests/test_geometry.py): 100% of `paper` and `street`
views, box and twobox, lifted to < 0.01 px with ratios < 0.1%, in about 5 ms. Before the
vanishing-point start, strongly perspective `paper` views failed in 3-6% of cases.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from cuboidtrain.geometry.camera_params import CORNER_SIDES, CameraParams, canonical, project, project_with_jacobian, rotation_vector
from cuboidtrain.geometry.intrinsics import CameraTerms, KnownCamera
from cuboidtrain.geometry.vanishing import vanishing_starts
from shared.shapes import Shape

# Perspective-strength starts (k = height / distance), tried group by group until one
# reaches ACCEPT_RMS: the second group raised exact `paper` lifts from 84% to 94% (box) and
# from 77% to 87% (twobox) at about twice the time; `street` never needs it.
K_STARTS = ((0.0, 0.15, 0.3, 0.5), (0.75, 1.0, 1.5))
ACCEPT_RMS = 1e-6  # px
# The best hypothesis polished on its own: near-frontal views sit in a flat valley where
# 300 batched iterations reproduce the corners to < 0.01 px with ratios still 1-200% off;
# 1000 more on one row (cheap) brought 13 of 18 exact `paper` failures to 1e-10.
POLISH_ITERATIONS = 1000


@dataclass(frozen=True)
class Solved:
    """LM result per hypothesis: params (B, P) and final cost (B,) = 0.5 * sum of squares; and, at
    those params, the normal equations' J^T J (B, P, P) of the M residuals a row has (what the
    Laplace approximation of the solution reads: `uncertainty.spread`)."""

    params: np.ndarray
    cost: np.ndarray
    normal: np.ndarray
    residuals: int


def levenberg_marquardt(residual, x0: np.ndarray, iterations: int = 50, step: float = 1e-7,
                        tolerance: float = 1e-12, jacobian=None, enough: float = 0.0,
                        groups: np.ndarray | None = None) -> Solved:
    """Minimise 0.5 |residual(x, rows)|^2 for every row of x0 at once.

    `residual(x, rows)` maps (B', P) params and (B',) hypothesis indices to (B', M) residuals.
    `jacobian(x, rows)`, when given, returns the residuals and their Jacobian (B', M, P), or a function
    of no arguments that computes it (called only for a trial step that some row takes);
    without it, one call evaluates every hypothesis and every forward-difference column
    (B * (P + 1) rows): numpy's per-call cost is paid once per iteration, not per column.
    Every hypothesis stops once one reaches a cost of `enough` (the lift's exact match); with
    `groups` (B,) (the rows of several problems solved at once), every hypothesis of its group.
    """
    # An analytic Jacobian costs less than a second evaluation of the residuals at the same
    # point, so every trial step computes it, and a taken step (most are) needs no other;
    # forward differences cost P + 1 evaluations: only after a taken step.
    trial_jacobian = jacobian is not None
    if jacobian is None:
        jacobian = partial(_forward_differences, residual, step)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # a diverged trial step: costed inf, rejected
        return _solve(residual, jacobian, x0, iterations, tolerance, enough, trial_jacobian, groups)


def _forward_differences(residual, step: float, x: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    b, p = x.shape
    probe = np.repeat(x[:, None, :], p + 1, axis=1)
    probe[:, 1:] += np.eye(p) * step
    values = residual(probe.reshape(-1, p), np.repeat(rows, p + 1)).reshape(b, p + 1, -1)
    r = values[:, 0]
    return r, (values[:, 1:] - r[:, None]).transpose(0, 2, 1) / step


def _solve(residual, jacobian, x0: np.ndarray, iterations: int, tolerance: float, enough: float,
           trial_jacobian: bool, groups: np.ndarray | None) -> Solved:
    x = x0.copy()
    b, p = x.shape
    rows = np.arange(b)
    damping, growth = np.full(b, 1e-3), np.full(b, 2.0)
    active = np.ones(b, dtype=bool)
    jtj, grad = np.zeros((b, p, p)), np.zeros((b, p))

    def normal_equations(at: np.ndarray, r: np.ndarray, jac: np.ndarray) -> None:
        transposed = jac.transpose(0, 2, 1)
        jtj[at] = transposed @ jac
        grad[at] = (transposed @ r[..., None])[..., 0]

    if trial_jacobian:
        r, jac = jacobian(x, rows)
        normal_equations(rows, r, _computed(jac))
    else:
        r = residual(x, rows)
    cost, count = 0.5 * (r**2).sum(1), r.shape[1]
    stale = np.full(b, not trial_jacobian)  # x moved since its normal equations were formed
    eye = np.eye(p)
    for _ in range(iterations):
        if not trial_jacobian and (redo := np.flatnonzero(active & stale)).size:
            # a rejected step leaves x, and so J, as they were: no new Jacobian
            normal_equations(redo, *jacobian(x[redo], redo))  # (B', M), (B', M, P)
            stale[redo] = False
        # Each live row's arrays read once a step, as views while every row is live (most steps): the
        # solver's numpy calls, not its rows, are its cost.
        live = active.nonzero()[0]  # np.flatnonzero's and np.diagonal's answers, without their wrappers
        at = slice(None) if len(live) == b else live
        jtj_live, grad_live, damping_live, cost_live = jtj[at], grad[at], damping[at], cost[at]
        scaled = damping_live[:, None] * (jtj_live.diagonal(0, 1, 2) + 1e-9)
        delta = -np.linalg.solve(jtj_live + scaled[:, :, None] * eye, grad_live[:, :, None])[..., 0]
        trial = x[at] + delta
        if trial_jacobian:  # the trial's Jacobian with its residuals: kept if the step is taken
            trial_r, trial_jac = jacobian(trial, live)
        else:
            trial_r = residual(trial, live)
        new_cost = 0.5 * (trial_r**2).sum(1)  # NaN for a diverged trial: its gain is NaN, not > 0, and it is rejected
        gain = cost_live - new_cost
        # Nielsen's damping update (Madsen, Nielsen & Tingleff 2004, sec. 3.2): by how well the
        # linear model predicted the gain; fewer rejected steps than a fixed /3, x4.
        predicted = 0.5 * (delta * (scaled * delta - grad_live)).sum(1)
        rho = gain / np.where(predicted > 0, predicted, np.inf)
        better = gain > 0
        every = better.all()  # every step taken (most often): no row picked out, no row's old values kept
        taken, kept = (at, slice(None)) if every else (live[better], better)
        x[taken] = trial[kept]
        if trial_jacobian:
            normal_equations(taken, trial_r[kept], _computed(trial_jac)[kept])
        else:
            stale[taken] = True
        shrunk = damping_live * np.maximum(1 / 3, 1 - (2 * rho - 1) ** 3)
        if every:
            cost_live, damping_live, growth_live = new_cost, shrunk, 2.0
        else:
            cost_live = np.where(better, new_cost, cost_live)
            damping_live = np.where(better, shrunk, damping_live * growth[at])
            growth_live = np.where(better, 2.0, growth[at] * 2)
        cost[at], damping[at], growth[at] = cost_live, damping_live, growth_live
        done = (better & (gain <= tolerance * (cost_live + 1e-12))) | (damping_live > 1e10) | (cost_live < 1e-20)
        active[live[done]] = False
        if enough > 0:
            _stop_groups_that_reached(active, cost, enough, groups)
        if not active.any():
            break
    if stale.any():  # forward differences: the last taken steps' normal equations, at the params returned
        redo = np.flatnonzero(stale)
        normal_equations(redo, *jacobian(x[redo], redo))
    return Solved(x, cost, jtj, count)


def _computed(jacobian) -> np.ndarray:
    """A Jacobian, or the one a deferred Jacobian (a function of no arguments) computes."""
    return jacobian() if callable(jacobian) else jacobian


def _stop_groups_that_reached(active: np.ndarray, cost: np.ndarray, enough: float, groups: np.ndarray | None) -> None:
    """Every row of a group (all rows without `groups`) stops once one of its rows costs < `enough`."""
    reached = cost < enough
    if groups is None:
        active &= ~reached.any()
        return
    hit = np.zeros(groups.max() + 1, dtype=bool)
    hit[groups[reached]] = True
    active &= ~hit[groups]


_SIDES = tuple(CORNER_SIDES[:, k].astype(bool) for k in range(3))  # each corner's LEFT, BOTTOM, FRONT


def _edge_means(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean 2D edge vectors of one labelled box (8, 2): toward RIGHT, BOTTOM and BACK."""
    left, bottom, front = _SIDES
    right_minus_left = points[~left].mean(0) - points[left].mean(0)
    down = points[bottom].mean(0) - points[~bottom].mean(0)
    back = points[~front].mean(0) - points[front].mean(0)
    return right_minus_left, down, back


def affine_box(points: np.ndarray) -> tuple[float, float, float, np.ndarray]:
    """Weak-perspective lift of one labelled box (8, 2): width, depth (height 1), scale s and
    the rotation's first two rows.

    In an affine view the image edge vectors are s R [w, 1, d] per axis; R's first two rows
    are orthonormal, which gives two linear equations in 1/w^2 and 1/d^2.
    """
    ux, uy, uz = _edge_means(points)
    a = np.array([[ux[0] * ux[1], uz[0] * uz[1]], [ux[0] ** 2 - ux[1] ** 2, uz[0] ** 2 - uz[1] ** 2]])
    rhs = -np.array([uy[0] * uy[1], uy[0] ** 2 - uy[1] ** 2])
    try:
        inv_w2, inv_d2 = np.linalg.solve(a, rhs)
    except np.linalg.LinAlgError:
        inv_w2 = inv_d2 = -1.0
    s = np.linalg.norm(uy)
    # Perspective or noise can make the system inconsistent: fall back to image lengths.
    w = 1 / np.sqrt(inv_w2) if inv_w2 > 0 else max(np.linalg.norm(ux) / s, 0.05)
    d = 1 / np.sqrt(inv_d2) if inv_d2 > 0 else max(np.linalg.norm(uz) / s, 0.05)
    rows = np.stack([ux / w, uy, uz / d], axis=1)  # (2, 3) = s * R[:2]
    s = np.sqrt(0.5 * (rows**2).sum())
    return w, d, s, rows / s


def _rotation_from_rows(rows: np.ndarray) -> np.ndarray:
    """The nearest rotation whose first two rows are `rows` (2, 3)."""
    m = np.vstack([rows, np.cross(rows[0], rows[1])])
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt


def affine_starts(points: np.ndarray, shape: Shape, k_starts=(0.0,)) -> tuple[np.ndarray, np.ndarray]:
    """Start params (H, P) and mirror flags (H,) from labelled image corners (N, 2): the two
    depth orders of the affine lift (R's third row +-; the - one is a rotation of the
    x-mirrored box) times each perspective strength in `k_starts`."""
    parts = [points[list(p)] for p in shape.parts]
    w, d, s, rows = affine_box(parts[0])
    extra = []
    if len(shape.parts) == 2:
        w_left, _, s_left, _ = affine_box(parts[1])
        h_left = s_left / s  # each part's affine lift sets its own height to 1
        width = w + w_left * h_left
        extra, w = [w / width, np.log(h_left)], width
    centre = points.mean(0)
    starts, mirrors = [], []
    rotation = _rotation_from_rows(rows)
    for mirror in (False, True):
        r = rotation
        if mirror:  # same first two rows for the reflected object: R F with R's third row negated
            r = np.vstack([r[:2], -r[2]]) @ np.diag([-1.0, 1.0, 1.0])
        vector = rotation_vector(r)
        for k in k_starts:
            starts.append([np.log(w), np.log(d), *vector, 0.0, 0.0, np.log(s), k, centre[0], centre[1], *extra])
            mirrors.append(mirror)
    params, mirror = np.array(starts), np.array(mirrors)
    # The object centre is not the corners' centroid (twobox, perspective): shift c to match.
    params[:, 9:11] += centre - project(params, shape, mirror).mean(1)
    return params, mirror


def corner_residuals(points: np.ndarray, sqrt_w: np.ndarray, shape: Shape, mirrors: np.ndarray,
                     cameras: CameraTerms | None = None, owner: np.ndarray | None = None):
    """The weighted reprojection residuals of hypotheses with flags `mirrors` (H,), each against
    its own corners `points` (H, N, 2) with weights `sqrt_w` (H, N, 1), and their analytic Jacobian;
    with `cameras`, each hypothesis also held to its input's (`owner` (H,)) given camera."""

    def residual(x, rows):
        r = ((project(x, shape, mirrors[rows]) - points[rows]) * sqrt_w[rows]).reshape(len(x), -1)
        return r if cameras is None else np.concatenate([r, cameras.terms(x, owner[rows], mirrors[rows], False)[0]], axis=1)

    def jacobian(x, rows):
        # A step of every row (most are) reads the rows' arrays as they are, not gathered.
        every = len(rows) == len(mirrors)
        flags, weight = (mirrors, sqrt_w) if every else (mirrors[rows], sqrt_w[rows])
        image, jac = project_with_jacobian(x, shape, flags)
        r = ((image - (points if every else points[rows])) * weight).reshape(len(x), -1)
        jac = (jac * weight[..., None]).reshape(len(x), r.shape[1], -1)
        if cameras is None:
            return r, jac
        held, d_held = cameras.terms(x, owner if every else owner[rows], flags)
        return np.concatenate([r, held], axis=1), np.concatenate([jac, d_held], axis=1)

    return residual, jacobian


@dataclass(frozen=True)
class Hypotheses:
    """Lift hypotheses of several corner sets solved at once: params (H, P), mirror flags (H,),
    final costs (H,) and the corner set each belongs to (H,), in order of the sets."""

    params: np.ndarray
    mirrors: np.ndarray
    costs: np.ndarray
    owner: np.ndarray

    def best(self, owner: int, count: int) -> np.ndarray:
        """The indices of corner set `owner`'s `count` cheapest hypotheses, cheapest first."""
        mine = np.flatnonzero(self.owner == owner)
        return mine[np.argsort(self.costs[mine])[:count]]


def hypotheses(points: np.ndarray, weights: np.ndarray, shape: Shape, k_starts=(0.0,), vanishing: bool = True,
               iterations: int = 300, tolerance: float = 0.0, accept_rms: float = ACCEPT_RMS,
               cameras: CameraTerms | None = None) -> Hypotheses:
    """Every start of K named corner sets (K, N, 2) (weights (K, N)), the vanishing-point ones
    (with `vanishing`) then the affine ones for each perspective strength in `k_starts`, solved
    by one batched LM on the weighted reprojection error: numpy's per-call cost paid once for
    all K. A set's hypotheses stop once one of them reproduces its corners to `accept_rms` px.
    `cameras`: the sets' camera rows (`intrinsics.CameraTerms`): each start moved onto its given
    camera and held there, and kept to a plausible one."""
    starts, flags, owner = [], [], []
    for k, corners in enumerate(points):
        affine, affine_flags = affine_starts(corners, shape, k_starts)
        if vanishing:
            algebraic, algebraic_flags = vanishing_starts(corners, shape)
            affine, affine_flags = np.concatenate([algebraic, affine]), np.concatenate([algebraic_flags, affine_flags])
        starts.append(affine)
        flags.append(affine_flags)
        owner.append(np.full(len(affine), k))
    starts, flags, owner = np.concatenate(starts), np.concatenate(flags), np.concatenate(owner)
    if cameras is not None:
        starts = cameras.start_from(starts, owner)
    sqrt_w = np.sqrt(weights)[owner][..., None]
    residual, jacobian = corner_residuals(points[owner], sqrt_w, shape, flags, cameras, owner)
    solved = levenberg_marquardt(residual, starts, iterations, tolerance=tolerance, jacobian=jacobian,
                                 enough=0.5 * points.shape[1] * accept_rms**2, groups=owner if len(points) > 1 else None)
    return Hypotheses(solved.params, flags, solved.cost, owner)


@dataclass(frozen=True)
class Lifted:
    """The best camera for given corners, and every hypothesis tried (for ambiguity checks
    and as starts of a mask fit)."""

    camera: CameraParams
    rms: float  # px, weighted reprojection error of the best hypothesis
    hypotheses: np.ndarray  # (H, P)
    mirrors: np.ndarray  # (H,)
    costs: np.ndarray  # (H,)


def lift(points: np.ndarray, shape: Shape, weights: np.ndarray | None = None, k_starts=K_STARTS,
         iterations: int = 300, tolerance: float = 0.0, accept_rms: float = ACCEPT_RMS,
         polish: int = POLISH_ITERATIONS, vanishing: bool = True, known: KnownCamera | None = None,
         frame: tuple[int, int] | None = None) -> Lifted:
    """Named image corners (N, 2) -> the camera + cuboid that projects onto them (weighted
    least squares; `weights` (N,) per corner, e.g. heat-map confidences).

    `k_starts` are groups of perspective-strength starts, tried in turn until one reaches
    `accept_rms` px (a flat tuple is one group); the best is then polished for `polish`
    more iterations and given k >= 0 (`geometry.canonical`). `known`: the camera, where given
    (held: `intrinsics.KnownCamera`); `frame`: the image's (H, W), to keep the camera plausible
    (`intrinsics.PlausibleRows`; None: unbounded)."""
    points = np.asarray(points, dtype=np.float64)
    return lift_many(points[None], shape, None if weights is None else np.asarray(weights)[None], k_starts,
                     iterations, tolerance, accept_rms, polish, vanishing, [known],
                     None if frame is None else [frame])[0]


def lift_many(points: np.ndarray, shape: Shape, weights: np.ndarray | None = None, k_starts=K_STARTS,
              iterations: int = 300, tolerance: float = 0.0, accept_rms: float = ACCEPT_RMS,
              polish: int = POLISH_ITERATIONS, vanishing: bool = True,
              known: Sequence[KnownCamera | None] | None = None,
              frames: Sequence[tuple[int, int]] | None = None) -> list[Lifted]:
    """`lift` of K corner sets (K, N, 2) at once (weights (K, N)): each group of starts solved for
    every set not yet reproduced, then every set's best polished, all in one solver each time.
    `known` (K): each set's given camera, or None; `frames` (K): each set's image (H, W)."""
    points = np.asarray(points, dtype=np.float64)
    cameras = CameraTerms.of(shape, known, frames)
    weights = np.ones(points.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    groups = k_starts if isinstance(k_starts[0], (tuple, list)) else (k_starts,)
    tried: list[list[tuple]] = [[] for _ in points]  # per set: (params, mirrors, costs) of each group tried
    pending = np.arange(len(points))
    for number, group in enumerate(groups):
        solved = hypotheses(points[pending], weights[pending], shape, group, vanishing and number == 0, iterations,
                            tolerance, accept_rms, cameras and cameras.subset(pending))
        reproduced = []
        for row, k in enumerate(pending):
            mine = solved.owner == row
            tried[k].append((solved.params[mine], solved.mirrors[mine], solved.costs[mine]))
            reproduced.append(np.sqrt(2 * solved.costs[mine].min() / points.shape[1]) < accept_rms)
        pending = pending[~np.array(reproduced)]
        if not len(pending):
            break
    params, mirrors, costs = ([np.concatenate([t[i] for t in per_set]) for per_set in tried] for i in range(3))
    best = [int(np.argmin(c)) for c in costs]
    flags = np.array([bool(m[b]) for m, b in zip(mirrors, best)])
    residual, jacobian = corner_residuals(points, np.sqrt(weights)[..., None], shape, flags, cameras,
                                          np.arange(len(points)))
    polished = levenberg_marquardt(residual, np.array([p[b] for p, b in zip(params, best)]), polish, tolerance=0.0,
                                   jacobian=jacobian)
    lifted = []
    for k, mirror in enumerate(flags):
        vector, mirror = canonical(polished.params[k], bool(mirror))
        rms = float(np.sqrt(2 * polished.cost[k] / points.shape[1]))
        lifted.append(Lifted(CameraParams(shape, vector, mirror), rms, params[k], mirrors[k], costs[k]))
    return lifted
