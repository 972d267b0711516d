"""Error bars of a fitted cuboid: the Laplace approximation of the solved least-squares problem,
calibrated by what the fit shows of its own error.

At the solution x of min 0.5 |r(x)|^2 (the mask fit's residuals, its corner pull, ratio anchor
and camera rows included), the parameters' covariance is approximated by

    Sigma = sigma^2 (J^T J)^-1,   sigma^2 = |r|^2 / (M - P)   (the residuals' own variance)

and each reported quantity's raw standard deviation follows by the delta method: the ratios
through `camera.log_ratio_jacobian` (sd of a ratio = ratio x sd of its log), the focal length
through log f = log s - log k, the yaw by a central difference of the pose's yaw. A given
intrinsic is held by a stiff row, so its sd comes out near 0 and the others grow where it no
longer trades.

The raw sd is 2-6 times too small, by a factor that differs with the mask: where the error is
the networks' (corners placed wrong with confidence, an occluded part guessed) or the trade of
focal length, distance and depth, not the outline's noise. No single scale serves clean and
noisy masks, street views and others (BENCHMARKS.md, "Error bars"), so each quantity's sd is

    sd = u sqrt(exp(2 c . x) + floor^2),   x = (1, log(raw / u), log outline rms, log k,
                                                |sin 2 yaw|, log corner gap, log start spread)

u the quantity's unit (the ratio or focal length itself, 1 degree for the yaw), k the fit's
perspective strength (weak perspective: focal length and depth trade), |sin 2 yaw| how oblique
the view is (a frontal view hides one face), the outline rms and corner gap (`Evidence`) in % of
the frame's side, and the start spread how far apart the lift's hypotheses put the focal length
(its log's range: where the corners admit several cameras, the focal length and the depth the fit
settled on are the less certain; without it the free focal length's sd could not serve `paper`
and `street` at once). The coefficients c are a least-squares fit of log |error| on x over
generated masks (paper-clean, paper, street; box, twobox), scaled and floored so that the truth
lies within one sd for 60-80% of the values and within two for at least 90% in each scene,
separately for a given and a fitted focal length (`benchmarks/calibration/bench_coverage.py --fit-from`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from cuboidtrain.geometry.camera_params import (MIRROR_X, WEAK_K, CameraParams, Evidence, Spread, log_ratio_jacobian, ratios,
                                         rotation_matrices)

FEATURES = ("raw", "outline_rms", "perspective", "oblique", "corner_gap", "start_spread")  # x after its 1
# Offsets inside the logs: below them a feature says nothing more (a fit with no outline residual,
# weak perspective, corners on the box, starts that agree)
RAW_LEAST, OUTLINE_LEAST, PERSPECTIVE_LEAST, GAP_LEAST, SPREAD_LEAST = 1e-9, 1e-3, 1e-3, 1e-2, 1e-2
YAW_STEP = 1e-5  # rad, the central difference of the yaw


@dataclass(frozen=True)
class Calibration:
    """One quantity's sd from its features: u sqrt(exp(2 c . (1, x)) + floor^2)."""

    coefficients: tuple[float, ...]  # c: the intercept, then one a feature (FEATURES)
    floor: float  # relative to the unit

    def sd(self, x: np.ndarray, unit) -> np.ndarray:
        """(Q,) sds of Q values from their features x (Q, len(FEATURES)) and units (Q,)."""
        c = np.asarray(self.coefficients)
        return np.asarray(unit) * np.sqrt(np.exp(2 * (c[0] + np.asarray(x) @ c[1:])) + self.floor**2)


# (focal length given, quantity) -> its calibration. Fitted on masks 0-399 of bench_accuracy's six
# validation spools (box and twobox pooled); BENCHMARKS.md, "Error bars", has the command, the
# coverage on them and on masks 400-599, which they were not fitted on. The given focal length's two
# were refitted on masks 0-599 once every clean fit settled on its silhouette (`mask_fit.SETTLE_ITERATIONS`):
# its clean errors halved, and the old ones held 87-93% of clean values within 1 sd; held out of
# 0-399 they put `paper` and `street` yaw at 88-89% within 2 sd, so all 600 masks fit them and
# bench_trust's `measure` seeds, never fitted on, judge them.
CALIBRATIONS = {
    (False, "ratio"): Calibration((0.416, 1.052, -0.444, -0.068, -0.039, 0.342, 0.017), 0.200),
    (True, "ratio"): Calibration((1.935, 1.034, 0.331, -0.050, -0.131, 0.262, 0.000), 0.000),
    (False, "yaw"): Calibration((0.464, 0.588, -0.063, -0.206, 1.085, 0.391, 0.095), 0.750),
    (True, "yaw"): Calibration((1.080, 0.635, 0.828, -0.334, 0.245, 0.340, 0.000), 0.000),
    (False, "focal"): Calibration((0.339, 0.596, -0.309, 0.072, -0.310, 0.372, 0.099), 0.000),
}

# The calibration above was fitted on 256 px masks; a smaller silhouette's error differs from what its
# features say (a corner is a few px; the outline's steps are a larger share of it). Each sd is
# multiplied by max(1, SIZE_REFERENCE_PX / px) ** a, px the silhouette's size (`silhouette.extent_px`),
# a fitted per (focal length given, quantity) on generated 64, 128 and 256 px masks fitted as `infer`
# fits them (benchmarks/calibration/bench_trust.py --fit; BENCHMARKS.md, "Error bars"); a silhouette of
# SIZE_REFERENCE_PX or more keeps the calibration's sd. The given focal length's two refitted with its
# calibration (2026-11-29); the others as before (their cells stayed in band).
SIZE_REFERENCE_PX = 128.0
SIZE_INFLATION = {(False, "ratio"): 0.20, (True, "ratio"): 0.35, (False, "yaw"): 0.35, (True, "yaw"): -0.05,
                  (False, "focal"): 0.45}


def inflation(focal_given: bool, kind: str, silhouette_px: float) -> float:
    """The factor a `kind` sd ("ratio", "yaw", "focal") of a silhouette `silhouette_px` across is scaled by."""
    return max(1.0, SIZE_REFERENCE_PX / max(silhouette_px, 1.0)) ** SIZE_INFLATION[focal_given, kind]


def spread(camera: CameraParams, squares: float, normal: np.ndarray, residuals: int, focal_given: bool,
           evidence: Evidence) -> Spread | None:
    """The standard deviations of `camera`'s ratios, yaw and focal length, from the solution's sum
    of squared residuals, its J^T J (P, P) and how many residuals there are (`lift.Solved`), and
    what else the fit shows (`evidence`); None where they are not finite (a degenerate fit)."""
    if not (math.isfinite(squares) and np.isfinite(normal).all()):
        return None
    covariance = laplace(normal, squares, residuals)
    vector = camera.vector
    log_ratios = log_ratio_jacobian(vector[None], camera.shape)[0]  # (R, P)
    values = ratios(vector[None], camera.shape)[0]
    raw_ratios = values * np.sqrt(np.maximum(np.einsum("rp,pq,rq->r", log_ratios, covariance, log_ratios), 0.0))
    yaw, yaw_gradient = _yaw_and_gradient(camera)
    raw_yaw = math.sqrt(max(yaw_gradient @ covariance @ yaw_gradient, 0.0))
    focal = camera.focal_px()
    raw_focal = None if focal_given or not math.isfinite(focal) else _raw_focal_sd(camera, covariance)
    raws = [*raw_ratios, raw_yaw, *([] if raw_focal is None else [raw_focal])]
    units = [*values, 1.0, *([] if raw_focal is None else [focal])]
    kinds = ["ratio"] * len(values) + ["yaw"] + ([] if raw_focal is None else ["focal"])
    # A given focal length holds every start to it: what spread is left is its row's give, not the corners' doubt.
    x = features(np.array(raws), np.array(units), camera, yaw,
                 replace(evidence, start_spread=0.0) if focal_given else evidence)
    sds = np.array([CALIBRATIONS[focal_given, kind].sd(row, unit) * inflation(focal_given, kind, evidence.silhouette_px)
                    for kind, row, unit in zip(kinds, x, units)])
    bars = Spread(sds[: len(values)], float(sds[len(values)]), None if raw_focal is None else float(sds[-1]), x)
    return bars if np.isfinite(sds).all() else None


def features(raw: np.ndarray, unit: np.ndarray, camera: CameraParams, yaw_deg: float, evidence: Evidence) -> np.ndarray:
    """(Q, len(FEATURES)): each quantity's raw sd relative to its unit, beside what the whole fit
    shows (`Evidence`, the perspective strength, how oblique the view is: its pose's yaw)."""
    relative = np.log(np.abs(raw) / np.maximum(np.abs(unit), 1e-300) + RAW_LEAST)
    shared = [math.log(max(evidence.outline_rms, 0.0) + OUTLINE_LEAST),
              math.log(abs(float(camera.vector[8])) + PERSPECTIVE_LEAST),
              abs(math.sin(math.radians(2 * yaw_deg))),
              math.log(max(evidence.corner_gap, 0.0) + GAP_LEAST),
              math.log(max(evidence.start_spread, 0.0) + SPREAD_LEAST)]
    return np.column_stack([relative, np.tile(shared, (len(relative), 1))])


def laplace(normal: np.ndarray, squares: float, residuals: int) -> np.ndarray:
    """(P, P): sigma^2 (J^T J)^-1, sigma^2 = squares / (M - P) the residuals' variance; a direction the
    problem does not fix at all (a zero column, the twobox's unused parameters) gets no variance, not infinity."""
    sigma2 = squares / max(residuals - len(normal), 1)
    scale = np.sqrt(np.maximum(np.diag(normal), 1e-300))
    inverse = np.linalg.pinv(normal / np.outer(scale, scale), rcond=1e-12) / np.outer(scale, scale)
    return sigma2 * inverse


def _raw_focal_sd(camera: CameraParams, covariance: np.ndarray) -> float:
    gradient = np.zeros(len(camera.vector))
    gradient[7], gradient[8] = 1.0, -1.0 / camera.vector[8]  # log f = log s - log |k|
    return camera.focal_px() * math.sqrt(max(gradient @ covariance @ gradient, 0.0))


def _yaw_and_gradient(camera: CameraParams) -> tuple[float, np.ndarray]:
    """The pose's yaw in degrees and d yaw / d params, by central differences on the rotation vector
    (the yaw depends on no other parameter), the seven rotations in one batch."""
    steps = np.zeros((7, len(camera.vector)))
    steps[1:4, 2:5], steps[4:7, 2:5] = YAW_STEP * np.eye(3), -YAW_STEP * np.eye(3)
    yaws = yaws_deg(camera, camera.vector + steps)
    gradient = np.zeros(len(camera.vector))
    gradient[2:5] = ((yaws[1:4] - yaws[4:7] + 180.0) % 360.0 - 180.0) / (2 * YAW_STEP)
    return float(yaws[0]), gradient


def yaws_deg(camera: CameraParams, vectors: np.ndarray) -> np.ndarray:
    """(B,) the pose's yaw (`CameraParams.pinhole`, of the k >= 0 twin: `canonical`) of parameter
    vectors (B, P) that share `camera`'s perspective strength k and mirror flag; a weak-perspective
    one's is its rotation's own yaw."""
    rotations = rotation_matrices(vectors[:, 2:5])
    k, mirror = float(camera.vector[8]), camera.mirror
    if abs(k) > WEAK_K:
        if k < 0:  # the depth-reversed twin's rotation, and its flag (`canonical`)
            rotations, mirror = np.diag([1.0, 1.0, -1.0]) @ rotations @ MIRROR_X, not mirror
        if mirror:  # as `pinhole` reads a reflected box's rotation
            rotations = MIRROR_X @ rotations @ MIRROR_X
    return np.degrees(np.arctan2(-rotations[:, 2, 0], rotations[:, 2, 2]))
