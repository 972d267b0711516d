"""What is known of the camera, as residual rows a solver adds: intrinsics given, held (nearly) fixed.

A silhouette fixes a box's outline, not its camera: focal length, distance and depth trade
against each other, and the principal point wanders (issue "3D you can trust"). Where the
user knows the camera (`infer --focal-px`, `--principal-px`, `--camera FILE`), these rows
hold the fit to it. In the parameter layout of `cuboidtrain.geometry.camera_params`, the focal
length is f = s / k (s = exp(p7), k = p8) and the principal point is (p9, p10); the rows are

    focal:      stiffness * (f_given * k / s - 1)        (0 where s / k = f_given; smooth at k = 0)
    principal:  stiffness * (c - c_given) / PRINCIPAL_PX

so a given camera costs as much as `stiffness` px of corner error per 1% of focal length (or
PRINCIPAL_PX of principal point) it is missed by: HELD is stiff enough to hold it to a few
hundredths of a percent, a smaller one is a loose prior.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from cuboidtrain.geometry.camera_params import rotated_points
from shared.shapes import Shape

HELD = 1000.0  # the stiffness of a given camera: held, not merely preferred
PRINCIPAL_PX = 1.0  # the principal point's residual unit
# A photo's EXIF focal length is a loose prior, not a given camera: EXIF rounds it to a whole mm
# (a 35 mm equivalent of 26 mm is 25.5-26.5: +-2%), a phone reports its main lens's focal length
# for a digital zoom or a crop, and a resize keeps it only when the mask is the photo's whole frame.
# One sd (EXIF_FOCAL_SD of the focal length, EXIF_PRINCIPAL_SIDES of the frame's longer side for
# the principal point at the photo's centre) costs as much as one corner 1 px off, as the typical
# camera's Gaussian (`TYPICAL_WEIGHT`) does.
EXIF_FOCAL_SD = 0.12
EXIF_PRINCIPAL_SIDES = 0.03


@dataclass(frozen=True)
class KnownCamera:
    """Intrinsics given for one input, in its own pixels: either or both (None: fitted)."""

    focal_px: float | None = None
    principal_px: tuple[float, float] | None = None
    stiffness: float = HELD  # the focal length's (and the principal point's, unless given below)
    principal_stiffness: float | None = None  # the principal point's, where it differs
    exif: tuple[str, ...] = ()  # what of it a photo's EXIF gave (a loose prior), not the user

    @property
    def focal_held(self) -> bool:
        """Whether the focal length is held (given by the user), not a loose prior (EXIF) or free."""
        return self.focal_px is not None and "focal_px" not in self.exif

    def source(self, name: str) -> str:
        """The record's word for intrinsic `name`: given (by the user), exif (a photo's), or fitted."""
        return "exif" if name in self.exif else "given" if name in self.given else "fitted"

    def __post_init__(self):
        if self.focal_px is not None and not (_finite(self.focal_px) and self.focal_px > 0):
            raise ValueError(f"focal_px {self.focal_px!r}: expected a positive, finite number (px)")
        principal = self.principal_px
        if principal is not None and not (isinstance(principal, (tuple, list)) and len(principal) == 2
                                          and all(_finite(v) for v in principal)):
            raise ValueError(f"principal_px {principal!r}: expected two finite numbers X Y (px)")

    @classmethod
    def of(cls, focal_px=None, principal_px=None) -> "KnownCamera":
        """From what a user wrote (JSON numbers, a list), checked (ValueError naming the value and what
        was expected), as floats."""
        checked = cls(focal_px, principal_px)
        return cls(None if focal_px is None else float(focal_px),
                   None if principal_px is None else (float(checked.principal_px[0]), float(checked.principal_px[1])))

    @property
    def given(self) -> tuple[str, ...]:
        """The record's names of what was given: focal_px, principal_px."""
        return tuple(name for name, value in (("focal_px", self.focal_px), ("principal_px", self.principal_px))
                     if value is not None)


def _finite(value) -> bool:
    """A real number, not a bool, finite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class CameraRows:
    """The given cameras of K inputs solved together (`KnownCamera`, or None: nothing given), as
    the rows each hypothesis adds to its residuals: three a row, zero where nothing is given."""

    focal: np.ndarray  # (K,) px; NaN where not given
    principal: np.ndarray  # (K, 2) px; NaN where not given
    stiffness: np.ndarray  # (K,) the focal length's
    principal_stiffness: np.ndarray  # (K,)

    @classmethod
    def of(cls, known) -> "CameraRows | None":
        """From a sequence of KnownCamera or None; None where no input has a camera given (the
        solver then adds no row, and its numbers stay those of a free fit, bit for bit)."""
        known = list(known)
        if all(k is None or not k.given for k in known):
            return None
        focal = np.array([np.nan if k is None or k.focal_px is None else k.focal_px for k in known], dtype=np.float64)
        principal = np.array([(np.nan, np.nan) if k is None or k.principal_px is None else k.principal_px
                              for k in known], dtype=np.float64).reshape(-1, 2)
        stiffness = np.array([HELD if k is None else k.stiffness for k in known], dtype=np.float64)
        principal_stiffness = np.array([HELD if k is None else k.stiffness if k.principal_stiffness is None
                                        else k.principal_stiffness for k in known], dtype=np.float64)
        return cls(focal, principal, stiffness, principal_stiffness)

    def terms(self, x: np.ndarray, owner: np.ndarray, derivatives: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """(B, 3) residuals (focal, principal x, y) of params (B, P) whose inputs are `owner` (B,),
        and their Jacobian (B, 3, P) with `derivatives`."""
        f, c, w, wc = self.focal[owner], self.principal[owner], self.stiffness[owner], self.principal_stiffness[owner]
        has_f, has_c = np.isfinite(f), np.isfinite(c[:, 0])
        s, k = np.exp(x[:, 7]), x[:, 8]
        f0, c0 = np.where(has_f, f, 0.0), np.where(has_c[:, None], c, 0.0)
        focal = np.where(has_f, w * (f0 * k / s - 1), 0.0)
        centre = np.where(has_c[:, None], wc[:, None] * (x[:, 9:11] - c0) / PRINCIPAL_PX, 0.0)
        values = np.concatenate([focal[:, None], centre], axis=1)
        if not derivatives:
            return values, None
        jac = np.zeros((len(x), 3, x.shape[1]))
        jac[:, 0, 7] = np.where(has_f, -w * f0 * k / s, 0.0)
        jac[:, 0, 8] = np.where(has_f, w * f0 / s, 0.0)
        jac[:, 1, 9] = jac[:, 2, 10] = np.where(has_c, wc / PRINCIPAL_PX, 0.0)
        return values, jac

    def subset(self, rows: np.ndarray) -> "CameraRows":
        """The cameras of inputs `rows`, renumbered 0 .. len(rows) - 1."""
        return CameraRows(self.focal[rows], self.principal[rows], self.stiffness[rows], self.principal_stiffness[rows])

    def start_from(self, params: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """Starts (H, P) of inputs `owner` (H,) moved onto their given cameras: the principal point
        set (the object kept where it was seen), k chosen so that s / k is the focal length."""
        moved = params.copy()
        c, f = self.principal[owner], self.focal[owner]
        has_c, has_f = np.isfinite(c[:, 0]), np.isfinite(f)
        shift = np.where(has_c[:, None], c - moved[:, 9:11], 0.0)
        moved[:, 9:11] += shift
        moved[:, 5:7] -= shift / np.exp(moved[:, 7:8])
        moved[:, 8] = np.where(has_f, np.exp(moved[:, 7]) / np.where(has_f, f, 1.0), moved[:, 8])
        return moved


# A plausible camera, where none is given (issue "3D you can trust", Must have 3). Measured on
# 300 generated 256 px views a scene and shape: the focal length over the frame's longer side
# is at least 0.22 (street; 1st percentile 0.36; paper 0.46), the principal point lies within
# 1.5 sides of the frame's centre (paper: up to 1.46 left, 1.28 above), and every corner's
# depth is at least 0.17 of the box centre's (street twobox; 1st percentile 0.34).
MIN_FOCAL_SIDES = 0.25  # a field of view of at most 127 degrees across the frame
PRINCIPAL_SIDES = 2.0  # the principal point within this many sides of the frame's centre
MIN_DEPTH_SHARE = 0.1  # no corner nearer than this share of the centre's distance: the camera is outside
PLAUSIBLE = 30.0  # the stiffness of the bounds: a hinge, 0 inside them
# Within the bounds, the typical camera: a Gaussian on kappa = side / f and on the principal point's
# offset from the frame's centre (in sides), fitted to the same views (paper and street pooled:
# kappa 0.50 +- 0.36 and 0.87 +- 0.54; cx 0.0 +- 0.6 and 0.0 +- 0.3; cy -0.5 +- 0.3 and -0.1 +- 0.3).
TYPICAL = np.array([0.6, 0.0, -0.3])  # kappa, cx, cy
TYPICAL_SD = np.array([0.5, 0.5, 0.45])
TYPICAL_PULL = 1.0 / TYPICAL_SD
TYPICAL_WEIGHT = 1.0  # one sd costs as much as one corner 1 px off


@dataclass(frozen=True)
class PlausibleRows:
    """The bounds of a plausible camera for K inputs solved together, as residual rows that are 0
    inside them: a focal length no shorter than MIN_FOCAL_SIDES of the frame, the principal point
    near the frame, every corner in front of the camera. Where an input's camera is given
    (`CameraRows`), its focal length and principal point are held instead and only the last applies."""

    side: np.ndarray  # (K,) px: each frame's longer side
    centre: np.ndarray  # (K, 2) px: each frame's centre
    free_focal: np.ndarray  # (K,) 1.0 where the focal length is fitted, else 0.0
    free_principal: np.ndarray  # (K,) 1.0 where the principal point is fitted, else 0.0
    stiffness: float = PLAUSIBLE
    typical: float = TYPICAL_WEIGHT  # the weight of the typical camera's Gaussian (0: bounds only)

    @classmethod
    def of(cls, frames, known=None) -> "PlausibleRows":
        """`frames`: each input's (H, W); `known`: each one's KnownCamera or None."""
        frames = np.asarray(frames, dtype=np.float64).reshape(-1, 2)
        known = list(known) if known is not None else [None] * len(frames)
        return cls(frames.max(1), frames[:, ::-1] / 2 - 0.5,
                   np.array([k is None or k.focal_px is None for k in known], dtype=np.float64),
                   np.array([k is None or k.principal_px is None for k in known], dtype=np.float64))

    def terms(self, x: np.ndarray, owner: np.ndarray, rotated_z: np.ndarray | None,
              derivatives: bool = True, front: bool | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """(B, 6 or 7) residuals of params (B, P) of inputs `owner` (B,) whose rotated corners have
        depths `rotated_z` (B, N) (object centre at 0, in height units; None: no in-front row, or with
        `front`, no corner near the camera: `CameraTerms._depths`), and their Jacobian. The in-front row
        is the nearest corner's; its derivative follows k only (the corners' depths held): enough to push
        a camera out of the building, and LM takes no step that raises the cost."""
        w, table = self.stiffness, self._table.take(owner, axis=0)  # take: a quarter of indexing's cost
        side, centre, free_focal, free_principal = table[:, 0], table[:, 1:3], table[:, 3], table[:, 4]
        # |k|: a hypothesis with k < 0 is the depth-reversed twin of one with k > 0 (`camera.canonical`).
        per_k = side / np.exp(x[:, 7])  # d kappa / d |k|
        kappa = per_k * np.abs(x[:, 8])  # the frame's side over the focal length
        offset = (x[:, 9:11] - centre) / side[:, None]
        front = rotated_z is not None if front is None else front
        values = np.empty((len(x), 6 + front))
        short = free_focal * (kappa > 1 / MIN_FOCAL_SIDES)
        values[:, 0] = w * short * (MIN_FOCAL_SIDES * kappa - 1)
        distance = np.abs(offset)
        outside = free_principal[:, None] * (distance > PRINCIPAL_SIDES)
        values[:, 1:3] = w * outside * (distance - PRINCIPAL_SIDES)
        near = front and rotated_z is not None
        if near:  # the nearest corner: 1 + k z is the same for both twins (each has z and k negated)
            share = 1.0 + (x[:, 8, None] * rotated_z).min(1)
            behind = share < MIN_DEPTH_SHARE
            values[:, 3] = w * behind * (MIN_DEPTH_SHARE - share) / MIN_DEPTH_SHARE
        elif front:  # every corner far in front: what the row above gives at z = 0 (0 x -0.9 / 0.1), and a 0 derivative
            values[:, 3] = -0.0
        values[:, -3] = table[:, 5] * (kappa - TYPICAL[0])  # the typical camera's pulls: `_table`
        values[:, -2:] = table[:, 7:9] * (offset - TYPICAL[1:])
        if not derivatives:
            return values, None
        jac = np.zeros((len(x), values.shape[1], x.shape[1]))
        d_kappa = per_k * np.sign(x[:, 8])
        jac[:, 0, 7], jac[:, 0, 8] = -w * MIN_FOCAL_SIDES * short * kappa, w * MIN_FOCAL_SIDES * short * d_kappa
        jac[:, 1, 9], jac[:, 2, 10] = (w * outside * np.sign(offset) / side[:, None]).T
        if near:  # the nearest corner's z is (share - 1) / k where it is behind (k is then not 0)
            jac[:, 3, 8] = np.where(behind, -w * (share - 1) / np.where(behind, x[:, 8], 1.0) / MIN_DEPTH_SHARE, 0.0)
        jac[:, -3, 7], jac[:, -3, 8] = table[:, 6] * kappa, table[:, 5] * d_kappa
        jac[:, -2, 9], jac[:, -1, 10] = table[:, 9:11].T
        return values, jac

    @cached_property
    def _table(self) -> np.ndarray:
        """(K, 11): side, centre x, centre y, free focal, free principal, and the typical camera's pulls
        as `terms` multiplies them (kappa's, its negative, the principal point's two, those over the
        side): what `terms` reads of its rows' inputs, in one lookup (it runs at every step of every solver)."""
        pull = TYPICAL_PULL * self.typical
        principal = pull[1:] * self.free_principal[:, None]
        return np.column_stack([self.side, self.centre, self.free_focal, self.free_principal, pull[0] * self.free_focal,
                                -pull[0] * self.free_focal, principal, principal / self.side[:, None]])

    def subset(self, rows: np.ndarray) -> "PlausibleRows":
        return PlausibleRows(self.side[rows], self.centre[rows], self.free_focal[rows], self.free_principal[rows],
                             self.stiffness, self.typical)


@dataclass(frozen=True)
class CameraTerms:
    """Every camera row a solver adds for one shape class's K inputs: the given cameras held
    (`CameraRows`) and the bounds of a plausible one (`PlausibleRows`)."""

    shape: Shape
    held: CameraRows | None
    plausible: PlausibleRows | None
    in_front: bool = True  # the plausible bounds include the nearest corner's (a mask fit's starts leave it out)

    @classmethod
    def of(cls, shape: Shape, known=None, frames=None, typical: float = TYPICAL_WEIGHT) -> "CameraTerms | None":
        """`known` (K): each input's KnownCamera or None; `frames` (K): each input's (H, W), for the
        plausible bounds (None: no bounds). None where there is nothing to add: a free fit's
        numbers stay those of a solver without camera rows, bit for bit."""
        held = CameraRows.of(known or [])
        plausible = None if frames is None else replace(PlausibleRows.of(frames, known), typical=typical)
        return None if held is None and plausible is None else cls(shape, held, plausible)

    def terms(self, x: np.ndarray, owner: np.ndarray, mirrors: np.ndarray,
              derivatives: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The rows (B, M) of params (B, P) of inputs `owner` (B,) with flags `mirrors` (B,), and their
        Jacobian (B, M, P) with `derivatives`."""
        parts = []
        if self.held is not None:
            parts.append(self.held.terms(x, owner, derivatives))
        if self.plausible is not None:
            depths = self._depths(x, mirrors) if self.in_front else None
            parts.append(self.plausible.terms(x, owner, depths, derivatives, self.in_front))
        if len(parts) == 1:  # the plausible bounds alone, most often: no copy
            return parts[0]
        values = np.concatenate([v for v, _ in parts], axis=1)
        return values, (np.concatenate([j for _, j in parts], axis=1) if derivatives else None)

    def _depths(self, x: np.ndarray, mirrors: np.ndarray) -> np.ndarray | None:
        """(B, N) the corners' depths about the box centre (height units), only where a corner could
        be near the camera: no corner is further from the centre than the box's half-diagonal, so
        where |k| times that leaves every corner past MIN_DEPTH_SHARE, zeros do (and cost nothing);
        None where no row's could (most steps: `PlausibleRows.terms` then writes the row as zeros give it)."""
        extents = np.exp(x[:, :2])  # width, depth; height 1 (a twobox's LEFT part: p12, below)
        reach = 0.5 * np.sqrt((extents**2).sum(1) + np.maximum(1.0, np.exp(x[:, 12]) if x.shape[1] > 12 else 1.0) ** 2)
        near = (1.0 - np.abs(x[:, 8]) * reach * 2.0 < MIN_DEPTH_SHARE).nonzero()[0]  # x2: the twobox's taller part
        if not len(near):
            return None
        depths = np.zeros((len(x), self.shape.num_keypoints))
        depths[near] = rotated_points(x[near], self.shape, mirrors[near])[..., 2]
        return depths

    def subset(self, rows: np.ndarray) -> "CameraTerms":
        return CameraTerms(self.shape, self.held and self.held.subset(rows),
                           self.plausible and self.plausible.subset(rows), self.in_front)

    def start_from(self, params: np.ndarray, owner: np.ndarray) -> np.ndarray:
        return params if self.held is None else self.held.start_from(params, owner)
