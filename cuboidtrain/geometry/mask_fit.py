"""Fit cuboids to binary masks at the inputs' own resolution, one mask or a batch of them at once:
the silhouette's residuals (`cuboidtrain.geometry.outline`), a pull toward the networks' corners by
their confidence, an anchor of the extents to the Tabulator's ratios, minimised by
`cuboidtrain.geometry.lift`'s Levenberg-Marquardt from the best lift hypotheses of each mask.

A batch (`fit_masks`) solves every mask's hypotheses as rows of one LM: each row reads its own
mask's outline points and distance field, corners and anchor, so numpy's per-call cost, which
dominates at a few hypotheses a mask, is paid once for all (`eval --cuboid` fits its batches so).
One mask (`fit_mask`) is a batch of one, and gives the same numbers as before batching.

Measured (docs/research/geometric-fit/RESULTS.md, 3a/3b): from true corners + 3 px noise on
clean masks, hull corners to a median 0.4-0.5 px; from the shipped networks' corners,
clean-mask medians improve strongly (box 2.8 -> 0.7 px) while noisy means barely move.

A fit that stops short of a clean mask's silhouette (a face seen nearly edge-on drawn on the wrong
side) is restarted (`reach_silhouette`) from its first fit (`first_fits`, `finished`: nothing fitted
twice) with its corners moved onto the mask's own hull and outline vertices, and turned about its
vertical axis, on the silhouette first; the restart whose silhouette's IoU is highest is kept, and
one still short is polished on (`polished`): on 200 held-out clean masks a class (BENCHMARKS.md,
"A fit that reaches the silhouette").
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from cuboidtrain.geometry.camera_params import (CameraParams, CuboidFit, Evidence, describe, log_ratio_jacobian,
                                      outline_corners, project, project_deferred, ratios, rotation_matrices,
                                      rotation_vector)
from cuboidtrain.geometry.edge_lines import outline_polygon, signed_area
from cuboidtrain.geometry.intrinsics import CameraTerms, KnownCamera
from cuboidtrain.geometry.lift import Hypotheses, Solved, hypotheses, levenberg_marquardt
from cuboidtrain.geometry.silhouette import confidence, coverage, extent_px
from cuboidtrain.geometry.uncertainty import spread
from cuboidtrain.geometry.outline import (Fields, MaskFitWeights, MaskTarget, StackedTargets, boundary_points,
                                          silhouette_terms)
from shared.shapes import Shape

LIFT_K_STARTS = (0.0, 0.3)  # the affine starts' perspective strengths, beside the vanishing-point ones
LIFT_ITERATIONS = 15  # enough to rank the starts; the mask fit goes on from the best
STARTS = 2  # lift hypotheses a mask fit starts from (one sticks now and then)
ITERATIONS = 12
# A fit whose silhouette explains the mask less than RESTART_IOU may have stopped short: a face seen
# nearly edge-on drawn on the wrong side, a hull corner left where the mask has none. A clean
# generated mask has a box of IoU about 1, which the first start missed on 8-15% of them (60 a
# class). Only a clean mask is restarted: its outline a polygon of at most RESTART_SIDES sides
# within SNAP_POLYGON_PX (clean generated masks have 4-11; noisy ones a median of 58-71, 93-95% over
# 16), and a fit of IoU at least RESTART_FLOOR. On noisy masks (40 a set and shape) restarts ran on
# nearly every mask, cost half as much again and moved the corners both ways. The floor was 0.95: a
# clean twobox's fit of IoU 0.88 (a part's bottom on the wrong side) restarted to 0.98.
RESTART_IOU = 0.99
RESTART_FLOOR = 0.85
RESTART_SIDES = 16
RESTART_ROUNDS = 2  # a restart kept and still short starts the next from itself
RESTART_STARTS = 1  # lift hypotheses a restart fits (beside the turned fits, 2 reached no more of 18 short masks)
# The fit turned about its own vertical axis and tilted about its width's, in degrees: a face seen
# nearly edge-on (a side, the roof) taken to the other side of its edge, where the first fit, in the
# silhouette's flat valley there, does not cross. 11 short clean twoboxes of a dev spool: 0 -> 5
# reached turned +-8 alone; the two clean boxes whose twobox (a seam) explained them better
# reached past it once tilted too (their roofs' slivers).
# On the silhouette first (`silhouette_first`), +-5, 10 and 20 reached 3 more of 41 short clean
# twoboxes of tuning seeds than +-10 (+-5 and 15, or 25: none; the third axis: none), 4 more of 6 on others.
RESTART_TURNS_DEG = (-20.0, -10.0, -5.0, 5.0, 10.0, 20.0)
RESTART_AXES = (1, 0)  # the box's own axes turned about: vertical, then across its width (`turned`)
# Outline points a restart's objective reads (the first fit's: MaskFitWeights.max_boundary_points,
# 120): one every 5-6 px of a twobox's outline misses the narrow face a short fit lacks (480 reached
# no more of 18 short masks than 240, at twice the cost).
RESTART_OUTLINE_POINTS = 240
# A restart is kept where its silhouette explains more of the mask's pixels than the fit's by this many
# (its IoU's gain times the mask's area): a polygonal mask with its edge pixels flipped at 3%
# (tests/test_edge_lines.py) restarted 0.9872 -> 0.9886 (21 px), its interior corners 1.0 -> 1.3 px off,
# the noise's pixels fitted, not the box's; on 64 px masks, whose fit from the true cuboid itself
# stops at IoU 0.98 (the objective's pixel steps: BENCHMARKS.md), a gain of 0.002 is 2-4 px, and such
# restarts moved the corners 1.61 / 1.16 -> 1.70 / 1.28 px.
RESTART_GAIN_PX = 32.0
# A restart and the polish after it (`polished`) read the silhouette first (`silhouette_first`): on a
# clean mask the outline is all the evidence, and the networks' pull and the Tabulator's anchor, a few
# px or percent off, held fits at IoU 0.98 where the silhouette reached 0.99 (clean twoboxes of seeds
# not benchmarked, with the turns below: 7 short of 200 -> 2; BENCHMARKS.md, "A fit that reaches the
# silhouette"). Not alone: with no pull at all the silhouette's valleys are flat (depth against focal
# length), and last-bit differences between runs of the same input (most likely numpy's SIMD sums,
# which follow memory alignment) moved a record by 1e-9 px in half of runs (tests/test_infer_run.py);
# at a tenth of the first fit's pull it is the same every run and reaches as many masks (tuning
# seeds' short twoboxes: 38 of 41 either way).
# The answer's error bars still read the first fits' objective at it (`on_first_objective`).
RESTART_PULL = 0.1  # the networks' pull and the ratio anchor in a restart, times the first fit's
POLISH_ITERATIONS = 30  # the LM's iterations polishing a fit still short after its restarts
# A clean mask's chosen fit that reached its silhouette settles on it too, in this many LM iterations,
# kept wherever its IoU rises at all (`settled_on_silhouette`, gain 0): the first fit reads the networks'
# pull and the occluders' asymmetry, which hold a clean fit's edges a pixel off. Bench seeds, 200 clean
# masks a class: corners' median 0.72 / 0.85 -> 0.56 / 0.53 px (box / twobox), depth/height with the
# camera given 3.5 / 3.6 -> 1.9 / 1.3% (BENCHMARKS.md, "Targets"); the clean boxes' mean rose 3.27 -> 3.47
# (a depth the silhouette leaves free drifts). Its cost is within the record's noise (1.56-1.57x the
# networks without it, 1.50-1.57x with it), its p90 64 -> 72-75 ms ("The whole record against the networks").
SETTLE_ITERATIONS = 10
SNAP_POLYGON_PX = 1.5  # the mask's hull simplified to a polygon this close (px) gives the restart's corners
SNAP_MERGE_PX = 6.0  # hull vertices closer than this are one corner's staircase
SNAP_INTERIOR_WEIGHT = 0.1  # an interior corner's weight in the restart's lift: it follows the outline's


def fit_mask(mask: np.ndarray | MaskTarget, shape: Shape, corners: np.ndarray, confidence: np.ndarray,
             prior_ratios: np.ndarray | None = None, weights: MaskFitWeights = MaskFitWeights(),
             starts: int = STARTS, iterations: int = ITERATIONS) -> CuboidFit:
    """Cuboid params that explain a binary mask (input resolution), started from the lift of the
    network corners (N, 2) (the `starts` best lift hypotheses) and pulled toward them by
    `confidence` (N,). `prior_ratios` (the network's ratio head, `shape.ratio_names` order)
    anchors the extents the outline leaves free: near-frontal views trade depth against yaw and
    focal length (RESULTS.md)."""
    target = mask if isinstance(mask, MaskTarget) else MaskTarget.of(mask, weights)
    return fit_masks([target], shape, corners[None], confidence[None], [prior_ratios], weights, starts, iterations)[0]


def fit_masks(targets: Sequence[MaskTarget], shape: Shape, corners: np.ndarray, confidence: np.ndarray,
              prior_ratios: Sequence[np.ndarray | None], weights: MaskFitWeights = MaskFitWeights(),
              starts: int = STARTS, iterations: int = ITERATIONS,
              known: Sequence[KnownCamera | None] | None = None, plausible: bool = False,
              networks: np.ndarray | None = None, reach: float | None = None) -> list[CuboidFit]:
    """`fit_mask` for K masks of one shape class at once: `targets` (K), corners (K, N, 2),
    confidence (K, N), prior_ratios (K) each (R,) or None; one CuboidFit a mask, in order.
    `known` (K): each mask's given camera (`intrinsics.KnownCamera`), held in the lift and the fit;
    `plausible`: every camera kept to a plausible one for its mask's frame (`intrinsics.PlausibleRows`).
    `networks` (K, N, 2): the networks' own corners where `corners` were moved from them
    (`fit.cuboid.outline_start`): the error bars' evidence reads the networks' (default `corners`);
    `reach`: the IoU below which a fit of a clean mask has stopped short (`reach_silhouette`; None: RESTART_IOU)."""
    return finished(first_fits(targets, shape, corners, confidence, prior_ratios, weights, starts, iterations, known,
                               plausible, networks), reach)


@dataclass(frozen=True)
class FirstFits:
    """K masks of one shape class fitted from their first starts (`first_fits`), before any restart and
    the error bars (`finished`): the objective's inputs, so that a restart goes on from here, and the answers."""

    targets: Sequence[MaskTarget]
    stacked: StackedTargets
    shape: Shape
    corners: np.ndarray  # (K, N, 2) the corners the fit is pulled toward
    confidence: np.ndarray  # (K, N) their pull
    prior_ratios: Sequence[np.ndarray | None]
    weights: MaskFitWeights
    cameras: CameraTerms | None
    known: Sequence[KnownCamera | None] | None
    networks: np.ndarray  # (K, N, 2) the networks' own corners (the error bars' evidence)
    starts: tuple[np.ndarray, ...]  # each mask's lift hypotheses (H_k, P), every one, not just those fitted
    iterations: int
    answers: tuple[Solution, ...]
    fits: tuple[CuboidFit, ...]

    def solve(self, owner: np.ndarray, mirrors: np.ndarray, params: np.ndarray, iterations: int) -> Solved:
        """Rows `params` (B, P) of masks `owner` (B,) (reflected where `mirrors`) taken `iterations` LM
        steps on these fits' objective, as one LM: a fit from elsewhere, a restart, a polish (0: only the
        cost and normal equations at `params`)."""
        residual, jacobian = _objective(self.stacked, self.shape, self.corners, self.confidence, self.prior_ratios,
                                        self.weights, owner, mirrors, self.cameras)
        return levenberg_marquardt(residual, params, iterations, tolerance=1e-7, jacobian=jacobian)


def first_fits(targets: Sequence[MaskTarget], shape: Shape, corners: np.ndarray, confidence: np.ndarray,
               prior_ratios: Sequence[np.ndarray | None], weights: MaskFitWeights = MaskFitWeights(),
               starts: int = STARTS, iterations: int = ITERATIONS,
               known: Sequence[KnownCamera | None] | None = None, plausible: bool = False,
               networks: np.ndarray | None = None) -> FirstFits:
    """`fit_masks`'s fits from the `starts` best lift hypotheses of each mask, one LM for them all."""
    cameras = CameraTerms.of(shape, known, [t.mask.shape for t in targets] if plausible else None, weights.camera)
    lifted = lift_starts(corners, confidence, shape, cameras)
    chosen = [lifted.best(k, starts) for k in range(len(targets))]
    rows = np.concatenate(chosen)
    owner, mirrors = lifted.owner[rows], lifted.mirrors[rows]
    stacked = StackedTargets.of(targets)
    residual, jacobian = _objective(stacked, shape, corners, confidence, prior_ratios, weights, owner, mirrors, cameras)
    solved = levenberg_marquardt(residual, lifted.params[rows], iterations, tolerance=1e-7, jacobian=jacobian)
    answers = tuple(Solution(solved, row, bool(mirrors[row])) for row in cheapest(solved.cost, chosen))
    fits = tuple(described(target, shape, a.camera(shape), weights) for target, a in zip(targets, answers))
    return FirstFits(targets, stacked, shape, corners, confidence, prior_ratios, weights, cameras, known,
                     corners if networks is None else networks,
                     tuple(lifted.params[lifted.owner == k] for k in range(len(targets))), iterations, answers, fits)


def finished(first: FirstFits, reach: float | None = None, clean: Sequence[bool] | None = None,
             error_bars: bool = True) -> list[CuboidFit]:
    """The first fits, each that stopped short of a clean mask's silhouette restarted (`reach_silhouette`),
    with their error bars (`uncertainty.spread`; `error_bars=False`: none yet, `with_error_bars`)."""
    answers, fits = reach_silhouette(first, reach, clean)
    if not error_bars:
        return fits
    return [with_error_bars(first, k, answer, fit) for k, (answer, fit) in enumerate(zip(answers, fits))]


def with_error_bars(first: FirstFits, k: int, answer: Solution, fit: CuboidFit) -> CuboidFit:
    """Mask `k`'s `fit` (its LM `answer`, on `first`'s objective) with its error bars (`uncertainty.spread`):
    `finished`'s, or a caller's that needs them for one fit only (`fit.cuboid.FirstCuboid.with_error_bars`)."""
    known, camera = first.known, answer.camera(first.shape)
    focal_given = known is not None and known[k] is not None and known[k].focal_held  # EXIF's: a prior
    bars = spread(camera, 2 * answer.cost, answer.solved.normal[answer.row], answer.solved.residuals, focal_given,
                  evidence(camera, fit.residual_px, first.targets[k], first.networks[k], first.confidence[k],
                           first.starts[k]))
    return replace(fit, spread=bars)


def cheapest(cost: np.ndarray, chosen: Sequence[np.ndarray]) -> list[int]:
    """The row of least cost of each mask, whose rows lie one mask after another (`chosen`: each one's)."""
    ends = np.cumsum([len(mine) for mine in chosen])
    return [int(end - len(mine) + np.argmin(cost[end - len(mine) : end])) for end, mine in zip(ends, chosen)]


@dataclass(frozen=True)
class Solution:
    """One mask's chosen row of an LM solve: what the record and its error bars read."""

    solved: Solved
    row: int
    mirror: bool

    @property
    def cost(self) -> float:
        return float(self.solved.cost[self.row])

    def camera(self, shape: Shape) -> CameraParams:
        return CameraParams(shape, self.solved.params[self.row], self.mirror)


def fit_from(first: FirstFits, k: int, camera: CameraParams) -> CuboidFit:
    """Mask `k`'s fit on its first fits' objective, started from `camera` instead (an oracle's: the true
    cuboid, benchmarks/accuracy/bench_reach.py --oracle): how far the objective itself lets a fit reach."""
    solved = first.solve(np.array([k]), np.array([camera.mirror]), camera.vector[None].copy(), first.iterations)
    return described(first.targets[k], first.shape, CameraParams(first.shape, solved.params[0], camera.mirror),
                     first.weights)


def reach_silhouette(first: FirstFits, reach: float | None = None,
                     clean: Sequence[bool] | None = None) -> tuple[list[Solution], list[CuboidFit]]:
    """The first fits' answers and fits with every fit that stopped short of a clean mask's silhouette
    (IoU below `reach`) restarted (`restarted`, on the mask's outline read densely, `densely`, and the
    silhouette first, `silhouette_first`), then polished where still short (`polished`); a move
    kept where its silhouette explains more of the mask's pixels, by RESTART_GAIN_PX: its IoU, what the
    fit is to reach. Not the outline's rms: on a clean mask its pixels' staircase leaves it 0.3-0.5 px at
    the truth, and one short twobox of five looked at had a wrong fit of lower rms (0.34 px) than its
    true cuboid (0.52 px, IoU 1). One kept and still short is restarted again, RESTART_ROUNDS in all.
    `clean`: whether each mask is clean (`polygonal`), where the caller knows."""
    answers, fits, reach = list(first.answers), list(first.fits), RESTART_IOU if reach is None else reach
    below = [k for k, fit in enumerate(fits) if RESTART_FLOOR <= fit.iou < reach]  # none at reach 0: a first fit's
    area = {k: int(first.targets[k].mask.sum()) for k in below}  # the masks' pixels, counted only where asked
    # A mask whose fit misses fewer than RESTART_GAIN_PX of its pixels keeps it whatever a restart finds:
    # most 64 px masks (their fits miss 1.5% of some 1,200 px), none restarted in vain.
    short = [k for k in below if (1 - fits[k].iou) * area[k] > RESTART_GAIN_PX
             and (clean[k] if clean is not None else polygonal(first.targets[k].mask))]
    if not short:
        return answers, fits
    outline = replace(first, weights=silhouette_first(first.weights), stacked=StackedTargets.of(
        [densely(t) if k in short else t for k, t in enumerate(first.targets)]))

    def keep(moves: Sequence[tuple[int, Solution, CuboidFit]]) -> list[int]:
        """The masks whose fit a move explains better by RESTART_GAIN_PX, taken; those of them still short."""
        kept = [(k, again, other) for k, again, other in moves
                if (other.iou - fits[k].iou) * area[k] > RESTART_GAIN_PX]
        for k, again, other in kept:
            answers[k], fits[k] = on_first_objective(first, k, again), other
        return [k for k, _, other in kept if other.iou < reach]

    pending = short
    for _ in range(RESTART_ROUNDS):
        if not pending:
            break
        pending = keep([(k, *moved) for k, moved in zip(pending, restarted(outline, [answers[k] for k in pending],
                                                                            pending))])
    still = [k for k in short if fits[k].iou < reach]
    if still:
        keep([(k, *moved) for k, moved in zip(still, polished(outline, [answers[k] for k in still], still))])
    return answers, fits


def silhouette_first(weights: MaskFitWeights) -> MaskFitWeights:
    """`weights` with the networks' pull and the Tabulator's anchor scaled by RESTART_PULL: what a restart reads."""
    return replace(weights, corners=weights.corners * RESTART_PULL, ratios=weights.ratios * RESTART_PULL,
                   depth_ratio=weights.depth_ratio * RESTART_PULL)


def clean_silhouette(weights: MaskFitWeights) -> MaskFitWeights:
    """`silhouette_first`'s weights with the outline's misses weighed alike on both sides: what a clean mask's
    chosen fit still short of its silhouette settles on (`settled_on_silhouette`). Nothing hides part of a
    clean mask, so a point of its outline inside the silhouette is as much a miss as one outside; the
    occluders' asymmetry (`MaskFitWeights.inside`, `overhang`: half the weight, robust) moves every edge
    outward, to where fewer of the outline's staircase points are left outside. Started from the true
    cuboid (IoU 1) of the three clean twoboxes that stayed short (seed 42's, 256 px: BENCHMARKS.md), the
    restart's objective stopped at IoU 0.9896-0.9941; this one at 0.9949-0.9974."""
    return replace(silhouette_first(weights), inside=weights.outside, overhang=weights.outside)


def settled_on_silhouette(first: FirstFits, k: int, chosen: CuboidFit,
                          short: bool = True) -> tuple[Solution, CuboidFit] | None:
    """Mask `k`'s `chosen` fit (a clean mask's, its class chosen) fitted on by the LM on `clean_silhouette`,
    the outline read densely, as a row of `first`'s objective (`on_first_objective`: its error bars read the
    same objective as any fit's), and its fit; None where its silhouette explains no more of the mask's
    pixels than the gain asked: a fit still `short` of the silhouette after the restarts takes
    POLISH_ITERATIONS and must gain RESTART_GAIN_PX, one that reached it SETTLE_ITERATIONS and any gain.
    Only after the choice: weighed alike, a box fits a twobox's small step as well (64 px clean twoboxes:
    99% -> 96% called twobox when the restarts read these weights): the asymmetry is the choice's evidence there."""
    iterations, gain_px = (POLISH_ITERATIONS, RESTART_GAIN_PX) if short else (SETTLE_ITERATIONS, 0.0)
    target = first.targets[k]
    settle = replace(first, weights=clean_silhouette(first.weights), stacked=StackedTargets.of(
        [densely(t) if i == k else t for i, t in enumerate(first.targets)]))
    camera = chosen.camera
    solved = settle.solve(np.array([k]), np.array([camera.mirror]), camera.vector[None].copy(), iterations)
    fit = described(target, first.shape, CameraParams(first.shape, solved.params[0], camera.mirror), first.weights)
    if (fit.iou - chosen.iou) * int(target.mask.sum()) <= gain_px:
        return None
    return on_first_objective(first, k, Solution(solved, 0, camera.mirror)), fit


def polished(first: FirstFits, answers: Sequence[Solution], masks: Sequence[int]) -> list[tuple[Solution, CuboidFit]]:
    """For each of `masks`, its answer fitted on by POLISH_ITERATIONS more of the LM on `first`'s objective
    (a restart's: `silhouette_first`), one LM for them all, and its fit."""
    flags = np.array([a.mirror for a in answers])
    solved = first.solve(np.asarray(masks), flags, np.stack([a.solved.params[a.row] for a in answers]),
                         POLISH_ITERATIONS)
    moved = [Solution(solved, row, bool(flags[row])) for row in range(len(masks))]
    return [(a, described(first.targets[k], first.shape, a.camera(first.shape), first.weights))
            for k, a in zip(masks, moved)]


def on_first_objective(first: FirstFits, k: int, answer: Solution) -> Solution:
    """Mask `k`'s `answer`, found on a restart's objective, as a row of `first`'s (the LM's cost and normal
    equations at it, no step taken): its error bars (`uncertainty.spread`) read the same objective as a
    fit that was never restarted."""
    solved = first.solve(np.array([k]), np.array([answer.mirror]), answer.solved.params[answer.row][None].copy(), 0)
    return Solution(solved, 0, answer.mirror)


def densely(target: MaskTarget) -> MaskTarget:
    """`target` with RESTART_OUTLINE_POINTS of the mask's outline points (a clean mask's: none is an occluder's)."""
    return replace(target, outline=boundary_points(target.mask, RESTART_OUTLINE_POINTS))


def turned(camera: CameraParams, degrees: float, axis: int = 1) -> CameraParams:
    """The box turned about its own axis `axis` (through its centre: 1 vertical, 0 across its width) by
    `degrees`, right-handed."""
    turn, angle = np.eye(3), math.radians(degrees)
    a, b = (axis + 1) % 3, (axis + 2) % 3
    turn[a, a] = turn[b, b] = math.cos(angle)
    turn[a, b], turn[b, a] = -math.sin(angle), math.sin(angle)
    vector = camera.vector.copy()
    vector[2:5] = rotation_vector(rotation_matrices(vector[None, 2:5])[0] @ turn)
    return CameraParams(camera.shape, vector, camera.mirror)


def necker_twin(camera: CameraParams) -> CameraParams:
    """The box reflected in depth about its centre: under weak perspective the same picture with the
    other interior corner in front, so its outline's corners are other labels; the mirror flag
    toggled keeps the labels on the same image points (Z R F X = (Z R M) (M F) X, M the x mirror)."""
    depth, across = np.diag([1.0, 1.0, -1.0]), np.diag([-1.0, 1.0, 1.0])
    vector = camera.vector.copy()
    vector[2:5] = rotation_vector(depth @ rotation_matrices(vector[None, 2:5])[0] @ across)
    return CameraParams(camera.shape, vector, not camera.mirror)


def snapped_corners(camera: CameraParams, mask: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """A fit's corners (N, 2) in its solver's order moved onto the vertices of the mask's convex hull
    (`hull_vertices`), with the weights (N,) a lift gives them: 1 for a moved corner, the others
    (which follow in the lift) low. Two ways or three: the corners on their own hull moved in the same
    cyclic order as the mask's vertices, turned to where the pairs lie nearest, where both hulls
    have as many vertices; each corner on the hull moved to its nearest vertex (`nearest_snapped`);
    and a twobox's, whose outline is no convex polygon, each corner its fitted outline shows moved to
    the nearest convex vertex of the mask's outline (`convex_vertices`: a notch's side's corner)."""
    corners = camera.keypoints()
    on_hull = outline_polygon(corners)
    vertices = hull_vertices(mask)
    ways = []
    if len(vertices) == len(on_hull):
        shifts = [np.roll(vertices, -shift, axis=0) for shift in range(len(vertices))]
        snapped, weights = corners.copy(), np.full(len(corners), SNAP_INTERIOR_WEIGHT)
        snapped[on_hull] = min(shifts, key=lambda v: float(np.linalg.norm(v - corners[on_hull], axis=1).sum()))
        weights[on_hull] = 1.0
        ways.append((snapped, weights))
    ways.append(nearest_snapped(corners, on_hull, vertices))
    if len(camera.shape.parts) == 2:
        shown = np.flatnonzero(outline_corners(camera.shape, corners))
        ways.append(nearest_snapped(corners, shown, convex_vertices(mask)))
    return ways


def nearest_snapped(corners: np.ndarray, on_hull: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners (N, 2) each of `on_hull` moved to its nearest of the `vertices` (V, 2), the nearest pairs
    first, each vertex taken once, a vertex left over taking the nearest corner of the others (a face
    the fit shows edge-on); and their lift weights (`snapped_corners`)."""
    snapped, weights = corners.copy(), np.full(len(corners), SNAP_INTERIOR_WEIGHT)
    left = np.ones(len(vertices), dtype=bool)
    for group in (on_hull, np.setdiff1d(np.arange(len(corners)), on_hull)):
        distance = np.linalg.norm(corners[group][:, None] - vertices[None], axis=2)  # (corners, vertices)
        distance[:, ~left] = np.inf
        for flat in np.argsort(distance, axis=None):
            corner, vertex = np.unravel_index(flat, distance.shape)
            if np.isfinite(distance[corner, vertex]):
                snapped[group[corner]], weights[group[corner]], left[vertex] = vertices[vertex], 1.0, False
                distance[corner, :] = distance[:, vertex] = np.inf
    return snapped, weights


def polygonal(mask: np.ndarray) -> bool:
    """Whether the mask is one clean polygon: a single outline of at most RESTART_SIDES sides within
    SNAP_POLYGON_PX (contour noise and occluders' edges give dozens)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return len(contours) == 1 and len(cv2.approxPolyDP(contours[0], SNAP_POLYGON_PX, True)) <= RESTART_SIDES


def hull_vertices(mask: np.ndarray) -> np.ndarray:
    """(V, 2) px, counter-clockwise in the image (x right, y down): the mask's convex hull simplified
    to SNAP_POLYGON_PX, at pixel centres, a vertex within SNAP_MERGE_PX of the one before it
    dropped (a rasterised corner's staircase)."""
    points = cv2.findNonZero(mask.astype(np.uint8))
    return merged_polygon(cv2.approxPolyDP(cv2.convexHull(points), SNAP_POLYGON_PX, True))


def convex_vertices(mask: np.ndarray) -> np.ndarray:
    """(V, 2) px: the convex vertices of the mask's outline simplified as `hull_vertices` simplifies its
    hull, counter-clockwise. A union of two convex parts' outline turns inward only where their
    edges cross: its convex vertices are the parts' corners, its concave ones no corner's."""
    outlines, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    polygon = merged_polygon(cv2.approxPolyDP(max(outlines, key=cv2.contourArea), SNAP_POLYGON_PX, True))
    incoming, outgoing = polygon - np.roll(polygon, 1, axis=0), np.roll(polygon, -1, axis=0) - polygon
    return polygon[incoming[:, 0] * outgoing[:, 1] - incoming[:, 1] * outgoing[:, 0] > 0]


def merged_polygon(polygon: np.ndarray) -> np.ndarray:
    """(V, 2) px counter-clockwise in the image (x right, y down): an OpenCV polygon (V, 1, 2), a vertex
    within SNAP_MERGE_PX of the one kept before it or of the first dropped (a rasterised corner's staircase)."""
    polygon = polygon.reshape(-1, 2).astype(np.float64)
    kept = [polygon[0]]
    for vertex in polygon[1:]:
        if np.linalg.norm(vertex - kept[-1]) >= SNAP_MERGE_PX and np.linalg.norm(vertex - kept[0]) >= SNAP_MERGE_PX:
            kept.append(vertex)
    polygon = np.array(kept)
    return polygon if signed_area(polygon) >= 0 else polygon[::-1]


def restarted(first: FirstFits, answers: Sequence[Solution], masks: Sequence[int],
              starts: int = RESTART_STARTS) -> list[tuple[Solution, CuboidFit]]:
    """For each of `masks` (their answers so far), the fit whose silhouette explains its mask best (IoU,
    `best_explained`) of those solved as one LM on `first`'s objective (a restart's: `silhouette_first`,
    its `stacked` targets denser) from the `starts` best lift hypotheses of the answer's corners moved onto the
    mask's outline (`snapped_corners`, the answer's and its Necker twin's), and from the answer
    turned about its own axes (`turned`, RESTART_AXES by RESTART_TURNS_DEG)."""
    shape, cameras = first.shape, first.cameras
    ways = [(k, way) for a, k in zip(answers, masks) for camera in (a.camera(shape), necker_twin(a.camera(shape)))
            for way in snapped_corners(camera, first.targets[k].mask)]
    mask_of = np.array([k for k, _ in ways])
    subset = cameras and cameras.subset(mask_of)
    lifted = lift_starts(np.array([c for _, (c, _) in ways]), np.array([w for _, (_, w) in ways]), shape, subset)
    owner_mask = mask_of[lifted.owner]
    rows = np.concatenate([np.flatnonzero(owner_mask == k)[np.argsort(lifted.costs[owner_mask == k])[:starts]]
                           for k in masks])
    turns = [turned(a.camera(shape), degrees, axis) for a in answers for axis in RESTART_AXES
             for degrees in RESTART_TURNS_DEG]
    owner = np.concatenate([owner_mask[rows], np.repeat(masks, len(RESTART_AXES) * len(RESTART_TURNS_DEG))])
    flags = np.concatenate([lifted.mirrors[rows], [t.mirror for t in turns]]).astype(bool)
    params = np.concatenate([lifted.params[rows], np.reshape([t.vector for t in turns], (len(turns), -1))])
    solved = first.solve(owner, flags, params, first.iterations)
    return [best_explained(first.targets[k], shape, solved, np.flatnonzero(owner == k), flags, first.weights)
            for k in masks]


def best_explained(target: MaskTarget, shape: Shape, solved: Solved, rows: np.ndarray, flags: np.ndarray,
                   weights: MaskFitWeights) -> tuple[Solution, CuboidFit]:
    """Of a mask's `rows` of an LM solve, the one whose silhouette's IoU with the mask is highest, and its fit."""
    images = project(solved.params[rows], shape, flags[rows])
    row = int(rows[np.argmax([confidence(shape, image, target.mask) for image in images])])
    answer = Solution(solved, row, bool(flags[row]))
    return answer, described(target, shape, answer.camera(shape), weights)


def evidence(camera: CameraParams, outline_rms: float, target: MaskTarget, corners: np.ndarray,
             confidence: np.ndarray, starts: np.ndarray) -> Evidence:
    """What the error bars read beside the Laplace sd: the solved camera's outline rms (px) and the
    network's corners' (N, 2) distance from its box's, weighted as their pull is, each in % of the
    frame's side; and how far apart the lift hypotheses (H, P) the fit started among put the
    focal length (the range of their log focal lengths; a weak-perspective one counts as 1e12 px)."""
    side = max(target.mask.shape) / 100
    image = project(camera.vector[None], camera.shape, np.array([camera.mirror]))[0]  # the network's order
    weight = np.clip(confidence, 0.05, 1.0)
    gap = math.sqrt(float(np.sum(weight * np.sum((image - corners) ** 2, axis=1)) / np.sum(weight)))
    log_focal = starts[:, 7] - np.log(np.maximum(np.abs(starts[:, 8]), 1e-12))  # log f = log s - log |k|
    return Evidence(outline_rms / side, gap / side, float(np.ptp(log_focal)) if len(starts) else 0.0,
                    extent_px(target.mask))


def lift_starts(corners: np.ndarray, confidence: np.ndarray, shape: Shape,
                cameras: CameraTerms | None = None) -> Hypotheses:
    """The lift hypotheses of K corner sets (K, N, 2) (confidence (K, N)) that mask fits start
    from, each set's best first (`Hypotheses.best`): any optimiser's starts
    (`cuboidtrain.geometry.soft_mask_fit` starts from the same). `cameras`: the sets' given cameras."""
    # The starts are ranked, not final: the fit after them keeps every corner in front of the camera.
    # The rest of the camera's rows count here already: without them, the starts chosen were the free
    # fit's, and paper's depth/height median went back from 22-26% to 36-46% (40 masks a set).
    starts = None if cameras is None else replace(cameras, in_front=False)
    return hypotheses(corners, confidence, shape, LIFT_K_STARTS, vanishing=True, iterations=LIFT_ITERATIONS,
                      tolerance=1e-9, cameras=starts)


def _objective(stacked: StackedTargets, shape: Shape, corners: np.ndarray, confidence: np.ndarray,
               prior_ratios: Sequence[np.ndarray | None], weights: MaskFitWeights, owner: np.ndarray,
               mirrors: np.ndarray, cameras: CameraTerms | None = None):
    """The residuals and Jacobian functions of the hypotheses (rows) of every mask, each row
    reading its own mask's (`owner`) outline, field, corners and anchor (and given camera)."""
    # Boundary terms are normalised so the corner pull means the same whatever the outline length.
    norm = (1 / np.sqrt(stacked.count))[:, None]  # (K, 1)
    pull = weights.corners * np.sqrt(np.clip(confidence, 0.05, 1.0))[..., None]  # (K, N, 1)
    # ratio_names order: depth/height, width/height (per part): each pulled by its own weight.
    # A mask without a prior (the Tabulator's head gave a ratio <= 0) is not anchored: its rows are 0.
    anchored = np.array([p is not None for p in prior_ratios])
    any_anchored = bool(anchored.any())
    anchor = np.tile([weights.depth_ratio, weights.ratios], len(shape.parts))[None] * anchored[:, None]
    prior = np.array([p if p is not None else np.ones(2 * len(shape.parts)) for p in prior_ratios])
    # What each row reads of its mask, gathered once: a step of every row (most are) reads them as they are.
    padded = stacked.valid[owner] if not stacked.valid.all() else None  # None: no padding to zero (one mask's)
    by_row = RowArrays(owner, np.asarray(mirrors), stacked.outline[owner], padded,
                       corners[owner], pull[owner], norm[owner], anchor[owner], prior[owner],
                       stacked.fields.rows(owner), pull[owner] * norm[owner][..., None])

    def terms(x, mine, image, derivatives):
        """The residuals of rows `mine` (`RowArrays.of`), the silhouette rows' derivatives by image point (a
        function that computes them) and the camera rows' Jacobian (each camera row computed once, with its
        derivatives where they are asked for)."""
        fit, d_fit = silhouette_terms(image, shape, mine.outline, mine.fields, weights, derivatives, valid=mine.valid,
                                      deferred=True)
        pulled = ((image - mine.corners) * mine.pull).reshape(len(x), -1) * mine.norm
        extents = [mine.anchor * np.log(ratios(x, shape) / mine.prior)] if any_anchored else []
        held, d_held = cameras.terms(x, mine.owner, mine.mirrors, derivatives) if cameras is not None else (None, None)
        values = np.concatenate([fit * mine.norm, pulled, *extents, *([] if held is None else [held])], axis=1)
        return values, d_fit, d_held

    def residual(x, rows):  # a trial step needs no derivatives: the plain projection
        mine = by_row.of(rows)
        return terms(x, mine, project(x, shape, mine.mirrors), derivatives=False)[0]

    def jacobian(x, rows):
        """The residuals, and their Jacobian as a function of no arguments: the solver asks for it only where
        it takes the step (`lift.levenberg_marquardt`; a fifth of the first fits' steps take none)."""
        mine = by_row.of(rows)  # gathered once for the projection and the terms
        image, d_image = project_deferred(x, shape, mine.mirrors)
        values, d_fit, d_held = terms(x, mine, image, derivatives=True)

        def jac() -> np.ndarray:
            b, n, p = len(x), shape.num_keypoints, x.shape[1]
            image_jac = d_image()
            # (B, R, N x 2) @ (B, N x 2, P): numpy's matmul, several times faster than its einsum here
            rows_jac = [(d_fit().reshape(b, -1, 2 * n) @ image_jac.reshape(b, 2 * n, p)) * mine.norm[..., None],
                        (image_jac * mine.pulled_norm[..., None]).reshape(b, -1, p)]
            if any_anchored:
                rows_jac.append(mine.anchor[:, :, None] * log_ratio_jacobian(x, shape))
            if d_held is not None:
                rows_jac.append(d_held)
            return np.concatenate(rows_jac, axis=1)

        return values, jac

    return residual, jacobian


@dataclass(frozen=True)
class RowArrays:
    """What the objective's rows (`owner` (B,): each one's mask) read of their masks, one row each: the
    mirror flag, the outline and its padding, the corners and their pull, the norm, the extents' anchor and
    prior, the field, and the pull times the norm (the corner rows' Jacobian's factor)."""

    owner: np.ndarray
    mirrors: np.ndarray
    outline: np.ndarray
    valid: np.ndarray | None  # None: every outline point real (no padding)
    corners: np.ndarray
    pull: np.ndarray
    norm: np.ndarray
    anchor: np.ndarray
    prior: np.ndarray
    fields: Fields
    pulled_norm: np.ndarray

    def of(self, rows: np.ndarray) -> RowArrays:
        """Rows `rows` of these (the solver's live rows, sorted and distinct: as many as there are means all,
        returned as they are)."""
        if len(rows) == len(self.owner):
            return self
        owner, mirrors, outline, corners, pull, norm, anchor, prior = (
            v[rows] for v in (self.owner, self.mirrors, self.outline, self.corners, self.pull, self.norm, self.anchor,
                              self.prior))
        return RowArrays(owner, mirrors, outline, None if self.valid is None else self.valid[rows], corners, pull, norm,
                         anchor, prior, self.fields.rows(rows), self.pulled_norm[rows])


def described(target: MaskTarget, shape: Shape, camera: CameraParams, weights: MaskFitWeights) -> CuboidFit:
    """The record's view of one mask's best camera, with its outline residual and IoU (whatever
    optimiser found it)."""
    image = camera.keypoints()[None]  # computed once for this and `describe`
    outline_rms = float(np.sqrt(np.mean(silhouette_terms(image, shape, target.outline, target.sdf, weights)[0] ** 2)))
    iou, unexplained = coverage(shape, image[0], target.mask)
    return describe(camera, outline_rms, iou, unexplained)
