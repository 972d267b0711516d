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
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from cuboidtrain.geometry.camera_params import (CameraParams, CuboidFit, Evidence, describe, log_ratio_jacobian, project,
                                      project_with_jacobian, ratios)
from cuboidtrain.geometry.intrinsics import CameraTerms, KnownCamera
from cuboidtrain.geometry.lift import Hypotheses, hypotheses, levenberg_marquardt
from cuboidtrain.geometry.silhouette import confidence, extent_px
from cuboidtrain.geometry.uncertainty import spread
from cuboidtrain.geometry.outline import MaskFitWeights, MaskTarget, StackedTargets, silhouette_terms
from shared.shapes import Shape

LIFT_K_STARTS = (0.0, 0.3)  # the affine starts' perspective strengths, beside the vanishing-point ones
LIFT_ITERATIONS = 15  # enough to rank the starts; the mask fit goes on from the best
STARTS = 2  # lift hypotheses a mask fit starts from (one sticks now and then)
ITERATIONS = 12


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
              networks: np.ndarray | None = None) -> list[CuboidFit]:
    """`fit_mask` for K masks of one shape class at once: `targets` (K), corners (K, N, 2),
    confidence (K, N), prior_ratios (K) each (R,) or None; one CuboidFit a mask, in order.
    `known` (K): each mask's given camera (`intrinsics.KnownCamera`), held in the lift and the fit;
    `plausible`: every camera kept to a plausible one for its mask's frame (`intrinsics.PlausibleRows`).
    `networks` (K, N, 2): the networks' own corners where `corners` were moved from them
    (`fit.cuboid.outline_start`): the error bars' evidence reads the networks' (default `corners`)."""
    cameras = CameraTerms.of(shape, known, [t.mask.shape for t in targets] if plausible else None, weights.camera)
    lifted = lift_starts(corners, confidence, shape, cameras)
    chosen = [lifted.best(k, starts) for k in range(len(targets))]
    rows = np.concatenate(chosen)
    owner, mirrors = lifted.owner[rows], lifted.mirrors[rows]
    residual, jacobian = _objective(StackedTargets.of(targets), shape, corners, confidence, prior_ratios,
                                    weights, owner, mirrors, cameras)
    solved = levenberg_marquardt(residual, lifted.params[rows], iterations, tolerance=1e-7, jacobian=jacobian)
    networks = corners if networks is None else networks
    fits, first = [], 0
    for k, (target, mine) in enumerate(zip(targets, chosen)):
        best = first + int(np.argmin(solved.cost[first : first + len(mine)]))
        first += len(mine)
        camera = CameraParams(shape, solved.params[best], bool(mirrors[best]))
        focal_given = known is not None and known[k] is not None and known[k].focal_held  # EXIF's: a prior
        fit = described(target, shape, camera, weights)
        starts_k = lifted.params[lifted.owner == k]  # every lift hypothesis of this mask, not just those fitted
        bars = spread(camera, 2 * solved.cost[best], solved.normal[best], solved.residuals, focal_given,
                      evidence(camera, fit.residual_px, target, networks[k], confidence[k], starts_k))
        fits.append(replace(fit, spread=bars))
    return fits


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
    anchor = np.tile([weights.depth_ratio, weights.ratios], len(shape.parts))[None] * anchored[:, None]
    prior = np.array([p if p is not None else np.ones(2 * len(shape.parts)) for p in prior_ratios])

    def terms(x, rows, image, derivatives):
        """The residuals, the silhouette rows' derivatives by image point and the camera rows' Jacobian
        (each camera row computed once, with its derivatives where they are asked for)."""
        own = owner[rows]
        fit, d_fit = silhouette_terms(image, shape, stacked.outline[own], stacked.fields.rows(own), weights,
                                      derivatives, valid=stacked.valid[own])
        pulled = ((image - corners[own]) * pull[own]).reshape(len(x), -1) * norm[own]
        extents = [anchor[own] * np.log(ratios(x, shape) / prior[own])] if anchored.any() else []
        held, d_held = cameras.terms(x, own, mirrors[rows], derivatives) if cameras is not None else (None, None)
        values = np.concatenate([fit * norm[own], pulled, *extents, *([] if held is None else [held])], axis=1)
        return values, d_fit, d_held

    def residual(x, rows):  # a trial step needs no derivatives: the plain projection
        return terms(x, rows, project(x, shape, mirrors[rows]), derivatives=False)[0]

    def jacobian(x, rows):
        own = owner[rows]
        image, d_image = project_with_jacobian(x, shape, mirrors[rows])
        values, d_fit, d_held = terms(x, rows, image, derivatives=True)
        b, n, p = len(x), shape.num_keypoints, x.shape[1]
        # (B, R, N x 2) @ (B, N x 2, P): numpy's matmul, several times faster than its einsum here
        rows_jac = [(d_fit.reshape(b, -1, 2 * n) @ d_image.reshape(b, 2 * n, p)) * norm[own][..., None],
                    (d_image * (pull[own] * norm[own][..., None])[..., None]).reshape(b, -1, p)]
        if anchored.any():
            rows_jac.append(anchor[own][:, :, None] * log_ratio_jacobian(x, shape))
        if d_held is not None:
            rows_jac.append(d_held)
        return values, np.concatenate(rows_jac, axis=1)

    return residual, jacobian


def described(target: MaskTarget, shape: Shape, camera: CameraParams, weights: MaskFitWeights) -> CuboidFit:
    """The record's view of one mask's best camera, with its outline residual and IoU (whatever
    optimiser found it)."""
    image = project(camera.vector[None], shape, np.array([camera.mirror]))
    outline_rms = float(np.sqrt(np.mean(silhouette_terms(image, shape, target.outline, target.sdf, weights)[0] ** 2)))
    return describe(camera, outline_rms, iou=confidence(shape, image[0], target.mask))  # image[0]: camera.keypoints()
