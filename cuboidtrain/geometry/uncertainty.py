"""Error bars of a fitted cuboid: the Laplace approximation of the solved least-squares problem.

At the solution x of min 0.5 |r(x)|^2 (the mask fit's residuals, its corner pull, ratio anchor
and camera rows included), the parameters' covariance is approximated by

    Sigma = sigma^2 (J^T J)^-1,   sigma^2 = |r|^2 / (M - P)   (the residuals' own variance)

and each reported quantity's standard deviation follows by the delta method: the ratios through
`camera.log_ratio_jacobian` (sd of a ratio = ratio x sd of its log), the focal length through
log f = log s - log k, the yaw by a central difference of the pose's yaw. A given intrinsic is
held by a stiff row, so its sd comes out near 0 and the others grow where it no longer trades.

The raw Laplace sd is 3-6 times too small, and its tails too light, where the error is the
networks' (corners placed wrong with confidence, an occluded part guessed), not the outline's
noise: each quantity's sd is scaled, and a floor added in quadrature, sd = sqrt((a sd)^2 + b^2)
(the free camera's ratios: compressed, `free_ratio_sd`), calibrated on generated masks
(paper-clean, paper, street; box, twobox; camera free and given) so that the truth lies within
one sd for 60-80% of the values and within two for at least 90%, per scene (BENCHMARKS.md,
"Error bars", with the held-out checks).
"""
from __future__ import annotations

import math
import numpy as np

from cuboidtrain.geometry.camera import (CameraParams, Spread, canonical, euler_angles, log_ratio_jacobian, ratios,
                                         rotation_matrices)

RATIO_SCALE, RATIO_FLOOR = 7.1, 0.0  # the ratios, camera given: a, and b relative to the ratio
# The ratios, camera free: sd = sqrt((a r (raw / r)^p)^2 + (b r)^2), r the ratio. The Laplace sd
# says little where focal length, distance and depth trade: one scale a ratio left street's 86%
# within 1 sd and paper-clean's 67% (200 masks a set). Compressed (p 0.2) and floored at 14% of
# the ratio, each scene's lies in the band on masks the constants were not chosen on (chosen on
# masks 0-99 or 100-199: the same constants; BENCHMARKS.md, "Error bars").
FREE_RATIO_SCALE, FREE_RATIO_POWER, FREE_RATIO_FLOOR = 0.37, 0.2, 0.14
YAW_SCALE, YAW_FLOOR_DEG = 2.5, 3.4  # the yaw: a, and b in degrees
FOCAL_SCALE, FOCAL_FLOOR = 3.6, 0.36  # the focal length: a, and b relative to it
YAW_STEP = 1e-5  # rad, the central difference of the yaw


def spread(camera: CameraParams, squares: float, normal: np.ndarray, residuals: int,
           focal_given: bool) -> Spread | None:
    """The standard deviations of `camera`'s ratios, yaw and focal length, from the solution's sum
    of squared residuals, its J^T J (P, P) and how many residuals there are (`lift.Solved`); None
    where they are not finite (a degenerate fit)."""
    if not (math.isfinite(squares) and np.isfinite(normal).all()):
        return None
    covariance = laplace(normal, squares, residuals)
    vector = camera.vector
    log_ratios = log_ratio_jacobian(vector[None], camera.shape)[0]  # (R, P)
    values = ratios(vector[None], camera.shape)[0]
    ratio_sd = values * np.sqrt(np.maximum(np.einsum("rp,pq,rq->r", log_ratios, covariance, log_ratios), 0.0))
    yaw_gradient = _yaw_gradient(camera)
    yaw_sd = math.sqrt(max(yaw_gradient @ covariance @ yaw_gradient, 0.0))
    ratio_bars = (calibrated(ratio_sd, RATIO_SCALE, RATIO_FLOOR * values) if focal_given
                  else free_ratio_sd(ratio_sd, values))
    bars = Spread(ratio_bars, float(calibrated(yaw_sd, YAW_SCALE, YAW_FLOOR_DEG)),
                  None if focal_given else _focal_sd(camera, covariance))
    finite = np.isfinite(bars.ratios).all() and math.isfinite(bars.yaw_deg) and (bars.focal_px is None
                                                                                or math.isfinite(bars.focal_px))
    return bars if finite else None


def calibrated(raw, scale: float, floor):
    """sqrt((scale raw)^2 + floor^2): the Laplace sd scaled, with a floor for what it does not see."""
    return np.sqrt((scale * np.asarray(raw)) ** 2 + np.asarray(floor) ** 2)


def free_ratio_sd(raw, values):
    """The ratios' sd with the camera free, from their raw Laplace sd: compressed relative to each
    ratio and floored (FREE_RATIO_*)."""
    values = np.abs(np.asarray(values, dtype=float))
    relative = np.asarray(raw) / np.maximum(values, 1e-300)
    scaled = FREE_RATIO_SCALE * values * np.maximum(relative, 0.0) ** FREE_RATIO_POWER
    return np.sqrt(scaled**2 + (FREE_RATIO_FLOOR * values) ** 2)


def laplace(normal: np.ndarray, squares: float, residuals: int) -> np.ndarray:
    """(P, P): sigma^2 (J^T J)^-1, sigma^2 = squares / (M - P) the residuals' variance; a direction the
    problem does not fix at all (a zero column, the twobox's unused parameters) gets no variance, not infinity."""
    sigma2 = squares / max(residuals - len(normal), 1)
    scale = np.sqrt(np.maximum(np.diag(normal), 1e-300))
    inverse = np.linalg.pinv(normal / np.outer(scale, scale), rcond=1e-12) / np.outer(scale, scale)
    return sigma2 * inverse


def _focal_sd(camera: CameraParams, covariance: np.ndarray) -> float | None:
    focal = camera.focal_px()
    if not math.isfinite(focal):
        return None
    gradient = np.zeros(len(camera.vector))
    gradient[7], gradient[8] = 1.0, -1.0 / camera.vector[8]  # log f = log s - log |k|
    raw = focal * math.sqrt(max(gradient @ covariance @ gradient, 0.0))
    return float(calibrated(raw, FOCAL_SCALE, FOCAL_FLOOR * focal))


def _yaw_gradient(camera: CameraParams) -> np.ndarray:
    """d yaw_deg / d params by central differences on the rotation vector (the yaw depends on no other)."""
    gradient = np.zeros(len(camera.vector))
    for index in (2, 3, 4):
        step = np.zeros(len(camera.vector))
        step[index] = YAW_STEP
        ahead, behind = (_yaw(CameraParams(camera.shape, camera.vector + sign * step, camera.mirror)) for sign in (1, -1))
        gradient[index] = ((ahead - behind + 180.0) % 360.0 - 180.0) / (2 * YAW_STEP)
    return gradient


def _yaw(camera: CameraParams) -> float:
    pinhole = CameraParams(camera.shape, *canonical(camera.vector, camera.mirror)).pinhole()
    if pinhole is None:  # weak perspective: the rotation's own yaw
        return euler_angles(rotation_matrices(camera.vector[None, 2:5])[0])[1]
    return pinhole[0].pose.yaw_deg
