"""The `--cuboid` stage: a network candidate -> the perspective cuboid fitted to the input mask.

With `FitOptions(cuboid=True)` (`cuboidtrain infer --cuboid`) the Fitter hands every shape
class's Candidate here with the input component: the networks' corners, mapped back to the
input's pixels, start `cuboidtrain.geometry.mask_fit.fit_masks` at the input's own resolution and
pull the corners the outline leaves free, each weighted by its heat map's peak; the
Tabulator's ratios anchor the extents; the Refiner's completion speaks for the parts an
occluder hides (`cuboidtrain.fit.completion`). On a box whose outline is sharp, the corners its
edge lines fix (`cuboidtrain.geometry.edge_lines`: the vertices, and the interior where the
outline is a hexagon) take the networks' place in the start and the pull, weighed by their
variances (`outline_start`). The record's keypoints are then the fitted box's
projection, its ratios the box's own, and the shape class is chosen by the fitted
silhouettes' IoU with the input among the plausible fits (`choose_cuboid`).

Measured (BENCHMARKS.md, "infer --cuboid, second version"): better than the networks' corners on
every median, on 4 of 6 sets' means, in shape selection, yaw, width/height and 3D IoU; worse on
the box means of noisy `paper` and `street` and on `paper`'s depth/height. `infer`'s default
(`cli.INFER_CUBOID`); the library's FitOptions() stays the networks' chain.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cuboidtrain.fit.candidates import Candidate, choose
from cuboidtrain.fit.completion import completed_target
from cuboidtrain.geometry.camera_params import CuboidFit
from cuboidtrain.geometry.edge_lines import corners_from_edges, edge_lines, outline_polygon
from cuboidtrain.geometry.intrinsics import KnownCamera
from cuboidtrain.geometry import mask_fit
from cuboidtrain.geometry.mask_fit import FirstFits, finished, first_fits, polygonal
from cuboidtrain.geometry.outline import MaskTarget, bilinear
from shared.shapes import Shape, get_shape

# Shape selection from the fitted cuboids (Must have 4): each explains the input by its IoU,
# and a richer class must explain it better by this margin and be plausible. Measured on
# 1,200 held-out generated masks (BENCHMARKS.md, "Shape selection from the fitted cuboids"):
# the networks' margin (0.02) chose box for 12% of twobox masks; 0.005 alone chose twobox for
# 7% of box masks (occluders' notches); with the plausibility gate below, box 96.8% and
# twobox 94.8% (from 97.3% and 87.8%).
CUBOID_MARGIN = 0.005
# A twobox whose parts' heights differ by less than this share is a box with a seam: the
# generator draws the lower part at 35-85% of the taller's height, and a box fitted as a
# twobox comes out at 98% (median); true twoboxes at 58% (95th percentile 82%).
SEAM_HEIGHT_RATIO = 0.9
# A twobox whose narrower part is under this share of its width is a box with a sliver beside it: the
# generator draws each part at 30% of the width or more, and on irregular buildings (a neighbour's
# corner merged into one side, a chimney, a storey set back on the roof) the twobox's gain lies in such
# a sliver. Chosen on 150 masks a set and shape of the tuning seeds (`bench_accuracy.py --tuning-seeds`):
# 0.2 took irregular box masks called box from 80.7% to 88.7%, twoboxes unchanged (90.7%), street box
# 91.3 -> 92.7%, twobox 94.0 -> 93.3% (one mask), paper box 94.7 -> 97.3%, paper-clean unchanged;
# 0.25 gained 2 more irregular boxes and lost 2 twoboxes there and 2 on paper. Measured on bench_accuracy's
# own 200 a set and shape (BENCHMARKS.md, "Shape selection"): box masks called box +4.0 points on
# irregular, +2.5 street, +1.0 paper; twoboxes unchanged but on irregular (-1.5, 3 masks).
SLIVER_WIDTH_SHARE = 0.2
# A clean mask's fit, still short of its silhouette after the restarts, that explains less than this
# share of it went astray, at any size (a 64 px fit stops short of 0.99 on most clean masks, at 0.95-0.98):
# with a camera given, it is fitted again from the free camera's fit (`Fitter.freed`). 0.99 there moved
# most 64 px fits and took the given ratio's error bars out of band (2 sd: 91 -> 90%, bench_trust).
ASTRAY_IOU = 0.9
# An outline corner's score falls with its distance to the input's outline, at this scale:
# a clean 256 px mask puts its fitted corners within about 1 px of it (rasterised corners).
CORNER_SCORE_PX = 2.0
# The networks' corner error as a standard deviation, in model px, against which the outline's
# geometry is weighed (`outline_start`). Measured on 60 generated box masks a set (seeds 71-73, not
# bench_accuracy's; the edge lines' first version, Tukey at fixed scales, unweighed cracks): 1 model
# px gave clean box corners a mean of 3.6 px (4.3 without), 0.5 3.7, 2 3.6; on the noisy sets each
# was within the run-to-run scatter of the mean (about 0.5 px).
NETWORK_SD_MODEL_PX = 1.0
MIN_SD_PX = 0.25  # the outline's geometry is never taken as surer than this
# Outlines whose edge lines' median rms residual is above this (px) are left to the fit as it was: on
# bench_accuracy's noisy sets (line rms 0.8-1.6 px; clean masks' 0.27) the geometry moved the means
# both ways (`street` box, camera given, 6.75 -> 7.16 px; `paper` 7.67 -> 7.55), its error bars too
# narrow there: the contour noise's bumps are longer than the lines' spread says.
ROUGH_OUTLINE_PX = 0.5
# Which evidence placed a record's interior corners (the cuboid object's `interior`).
FROM_OUTLINE, FROM_HEAT_MAPS = "from outline", "from heat maps"


class NonFiniteCuboid(ValueError):
    """The cuboid fit gave NaN or Infinity where the record needs a number: no fit, and in
    `Fitter.outcomes` an error record (never a networks-only record in its place)."""


@dataclass(frozen=True)
class NoCuboid:
    """A batch row whose cuboid could not be fitted (`fit_candidates`), in its place: why."""

    reason: str  # one line, NonFiniteCuboid's message


@dataclass(frozen=True)
class FittedCuboid:
    """One shape class's cuboid fitted to the input, and how far each of its corners is seen."""

    fit: CuboidFit  # keypoints (N, 2) input px, viewer-named; ratios; angles; intrinsics; IoU
    corner_scores: np.ndarray  # (N,) in [0, 1], viewer-named (`corner_scores`)
    known: KnownCamera | None = None  # what was known of the camera (given, or a photo's EXIF), if anything
    interior: str = FROM_HEAT_MAPS  # FROM_OUTLINE where the outline's geometry led the interior corners

    @property
    def given(self) -> tuple[str, ...]:
        """The intrinsics known (`KnownCamera.given`), by the user or a photo's EXIF: focal_px, principal_px."""
        return self.known.given if self.known is not None else ()

    def source(self, name: str) -> str:
        """Where intrinsic `name` came from: given, exif or fitted (`KnownCamera.source`)."""
        return self.known.source(name) if self.known is not None else "fitted"

    def ratios_sd(self) -> dict | None:
        """The standard deviations of the ratios, shaped as the record's `ratios` (None: no error bars)."""
        spread = self.fit.spread
        return None if spread is None else get_shape(self.fit.shape).ratio_dict(spread.ratios)

    def record(self) -> dict:
        """The infer record's `cuboid` object (docs/contract.md, "The cuboid object")."""
        fit = self.fit
        perspective = math.isfinite(fit.focal_px)  # inf: weak perspective, no focal length or principal point
        spread = fit.spread
        return {"yaw_deg": fit.yaw_deg, "yaw_sd_deg": None if spread is None else spread.yaw_deg,
                "pitch_deg": fit.pitch_deg, "roll_deg": fit.roll_deg,
                "focal_px": fit.focal_px if perspective else None,
                "focal_sd_px": None if spread is None or not perspective else spread.focal_px,
                "principal_px": list(fit.principal_px) if perspective else None,
                "intrinsics": {name: self.source(name) for name in ("focal_px", "principal_px")},
                "mirror": fit.mirror, "iou": fit.iou, "outline_rms_px": fit.residual_px, "interior": self.interior,
                "corners": [{"on_outline": bool(on), "score": float(s)}
                            for on, s in zip(fit.on_outline, self.corner_scores)]}


def fit_candidates(candidates: Sequence[Candidate], masks: Sequence[np.ndarray | MaskTarget],
                   completion: bool = True, optimizer: str = "lm",
                   known: Sequence[KnownCamera | None] | None = None,
                   plausible: bool = False, reach: float | None = None) -> list[FittedCuboid | NoCuboid]:
    """The cuboid of each candidate's class fitted to its mask (H, W) bool, the input component (or
    its MaskTarget, shared by the shape classes tried), each shape class's fits solved as one
    batch (`mask_fit.fit_masks`), or one by one by the soft-rasterised fit (`optimizer="soft"`,
    `soft_mask_fit.fit_soft`); a fit that is not finite is a NoCuboid saying why, in its place.
    `completion=False` leaves the Refiner's completion out (benchmarks/accuracy/bench_cuboid_fit.py).
    `known`: each pair's given camera (or None), held by the fit (LM only); `plausible`: every
    camera kept to a plausible one (`intrinsics.PlausibleRows`); `reach`: the IoU below which a clean
    mask's fit restarts (`mask_fit.reach_silhouette`, LM only)."""
    if any(c.framing is None for c in candidates):
        raise ValueError("a cuboid fit needs the candidate's framing: the map back to the input's pixels")
    targets = [m if isinstance(m, MaskTarget) else MaskTarget.of(m) for m in masks]
    known = list(known) if known is not None else [None] * len(candidates)
    fitted: list = [None] * len(candidates)
    for name in dict.fromkeys(c.shape for c in candidates):
        batch = [i for i, c in enumerate(candidates) if c.shape == name]
        starts = [outline_start(fit_start(candidates[i], targets[i], completion), targets[i].mask, get_shape(name),
                                candidates[i].framing.scale, targets[i].cracks) for i in batch]
        fits = _solve(starts, get_shape(name), optimizer, [known[i] for i in batch], plausible, reach)
        for i, fit, start in zip(batch, fits, starts):
            fitted[i] = settled(fit, start, targets[i].sdf, known[i])
    return fitted


def settled(fit: CuboidFit, start: FitStart, sdf: np.ndarray, known: KnownCamera | None) -> FittedCuboid | NoCuboid:
    """A fit from `start` as the record's FittedCuboid, its corners scored on the input's outline (`sdf`,
    `corner_scores`); a NoCuboid saying why where a number of it is not finite."""
    try:
        check_finite(fit)
    except NonFiniteCuboid as exc:
        return NoCuboid(str(exc))
    named_peaks = start.peaks[fit.camera.naming()]  # the fit's corner i is the network's corner naming()[i]
    return FittedCuboid(fit, corner_scores(fit, sdf, named_peaks), known, start.interior)


@dataclass(frozen=True)
class FirstCuboid:
    """One candidate's cuboid fitted from its first start alone (`first_cuboid`), and what a restart
    goes on from (`reached`): the Fitter restarts a class only where the choice needs it, and gives the
    error bars only to the class it chose (`with_error_bars`: the choice reads none)."""

    cuboid: FittedCuboid | NoCuboid  # the LM's without its error bars (spread None): `with_error_bars`
    start: FitStart
    sdf: np.ndarray  # the input's signed distance field (`corner_scores`)
    known: KnownCamera | None
    first: FirstFits | None  # the LM's first fit; None: the soft optimiser's, never restarted

    def with_error_bars(self) -> FittedCuboid | NoCuboid:
        """`cuboid` with its error bars, as `mask_fit.finished` gives them (the soft optimiser's has its own)."""
        if self.first is None or isinstance(self.cuboid, NoCuboid):
            return self.cuboid
        fit = mask_fit.with_error_bars(self.first, 0, self.first.answers[0], self.cuboid.fit)
        return replace(self.cuboid, fit=fit)

    def reached(self, reach: float) -> FittedCuboid | NoCuboid:
        """The cuboid of a clean mask (`stopped_short` said so) restarted where it stopped short of its
        silhouette (IoU below `reach`, `mask_fit.reach_silhouette`), from its first fit: nothing fitted twice."""
        if self.first is None:
            return self.cuboid
        return settled(finished(self.first, reach, clean=[True])[0], self.start, self.sdf, self.known)

    def settled_on_silhouette(self, cuboid: FittedCuboid, short: bool = True) -> FittedCuboid | None:
        """`cuboid`, this class's chosen cuboid of a clean mask, settled on its silhouette
        (`mask_fit.settled_on_silhouette`: at length where it is still `short` of it, else briefly) with its
        error bars; None where that explains the mask no better."""
        if self.first is None:
            return None
        moved = mask_fit.settled_on_silhouette(self.first, 0, cuboid.fit, short)
        if moved is None:
            return None
        fit = mask_fit.with_error_bars(self.first, 0, *moved)
        return settled(fit, self.start, self.sdf, self.known)


def first_cuboid(candidate: Candidate, target: MaskTarget, optimizer: str = "lm", known: KnownCamera | None = None,
                 plausible: bool = False) -> FirstCuboid:
    """`fit_candidates` for one candidate (the input's `target`, its completion, its outline start), from
    its first start alone (reach 0: no restart), kept for `FirstCuboid.reached`; without its error bars
    (`FirstCuboid.with_error_bars`)."""
    if candidate.framing is None:
        raise ValueError("a cuboid fit needs the candidate's framing: the map back to the input's pixels")
    shape = get_shape(candidate.shape)
    start = outline_start(fit_start(candidate, target), target.mask, shape, candidate.framing.scale, target.cracks)
    if optimizer == "soft":
        [fit] = _solve([start], shape, optimizer, [known])
        return FirstCuboid(settled(fit, start, target.sdf, known), start, target.sdf, known, None)
    first = _first_fits([start], shape, [known], plausible)
    fit = finished(first, 0.0, error_bars=False)[0]  # no restart (reach 0), no error bars yet
    return FirstCuboid(settled(fit, start, target.sdf, known), start, target.sdf, known, first)


def _solve(starts: Sequence[FitStart], shape: Shape, optimizer: str,
           known: Sequence[KnownCamera | None], plausible: bool = False, reach: float | None = None) -> list[CuboidFit]:
    """The fits of one shape class's starts by `optimizer` (FitOptions.optimizer), each held to its
    given camera, if any (LM only: FitOptions refuses a camera with the soft optimiser)."""
    if optimizer == "soft":
        from cuboidtrain.geometry.soft_mask_fit import fit_soft  # torch's autograd: only when asked for

        return [fit_soft(s.target, shape, s.corners, s.peaks, prior_ratios=s.prior_ratios).fit for s in starts]
    return finished(_first_fits(starts, shape, known, plausible), reach)


def _first_fits(starts: Sequence[FitStart], shape: Shape, known: Sequence[KnownCamera | None],
                plausible: bool) -> FirstFits:
    """One shape class's starts fitted by LM from their first starts (`mask_fit.first_fits`)."""
    return first_fits([s.target for s in starts], shape, np.array([s.corners for s in starts]),
                      np.array([s.peaks for s in starts]), [s.prior_ratios for s in starts], known=known,
                      plausible=plausible, networks=np.array([s.network_corners() for s in starts]))


@dataclass(frozen=True)
class FitStart:
    """What a mask fit takes from a network candidate and the input, in the input's pixels:
    any optimiser's inputs (`mask_fit.fit_masks`; `soft_mask_fit.fit_soft`, measured against it)."""

    target: MaskTarget  # the input's, with the Refiner's completion (`completion.completed_target`)
    corners: np.ndarray  # (N, 2) input px, the network's corner order
    peaks: np.ndarray  # (N,) heat-map peaks: each corner's pull
    prior_ratios: np.ndarray | None  # `ratio_prior`
    interior: str = FROM_HEAT_MAPS  # what placed the interior corners' pull (`outline_start`)
    networks: np.ndarray | None = None  # (N, 2) the networks' corners where `corners` moved from them

    def network_corners(self) -> np.ndarray:
        """(N, 2) the networks' own corners, which the error bars' evidence reads (`mask_fit.evidence`)."""
        return self.corners if self.networks is None else self.networks


def fit_start(candidate: Candidate, target: MaskTarget, completion: bool = True) -> FitStart:
    """The candidate's corners mapped back to the input, their peaks, its ratio prior, and the
    input's target completed by its Refiner (`completion=False`: the input's own)."""
    return FitStart(completed_target(candidate, target) if completion else target,
                    candidate.framing.to_input(candidate.keypoints), heatmap_peaks(candidate.heatmaps),
                    ratio_prior(candidate))


def outline_start(start: FitStart, mask: np.ndarray, shape: Shape, model_scale: float,
                  every: tuple[np.ndarray, np.ndarray] | None = None) -> FitStart:
    """`start` with each corner its box's outline fixes moved toward where the input mask's edge lines
    put it (`edge_lines.corners_from_edges`, the outline split by the networks' corners' polygon):
    the two estimates weighed by their variances, the networks' NETWORK_SD_MODEL_PX model px
    (`model_scale`: model px a input px). The fit starts from and is pulled toward the result, so
    that where the outline fixes the interior, its geometry leads. Boxes only (a twobox's outline
    is no convex polygon), and outlines no rougher than ROUGH_OUTLINE_PX. `every`: the mask's cracks, where
    the caller has them (`MaskTarget.cracks`)."""
    if len(shape.parts) != 1:
        return start
    corners = start.corners
    edges = edge_lines(mask, corners, outline_polygon(corners), every)
    if not np.median([line.rms_px if line is not None else np.inf for line in edges.lines]) <= ROUGH_OUTLINE_PX:
        return start
    fixed = corners_from_edges(edges, shape)
    network_var = (NETWORK_SD_MODEL_PX / model_scale) ** 2
    share = np.where(fixed.from_outline, network_var / (network_var + np.maximum(fixed.sd_px, MIN_SD_PX) ** 2), 0.0)
    moved = np.where(fixed.from_outline[:, None], fixed.keypoints, corners)
    interior = ~fixed.on_outline
    decided = bool(interior.any() and (share[interior] > 0.5).all())
    return replace(start, corners=corners + share[:, None] * (moved - corners), networks=corners,
                   interior=FROM_OUTLINE if decided else FROM_HEAT_MAPS)


def ratio_prior(candidate: Candidate) -> np.ndarray | None:
    """The Tabulator's ratios (`ratio_names` order) that anchor the fit's extents; None when one
    is <= 0 or not finite: the head is unbounded, and such a ratio's log anchors nothing."""
    prior = get_shape(candidate.shape).ratio_vector(candidate.ratios)
    return prior if (prior > 0).all() and np.isfinite(prior).all() else None


def implausible(fit: CuboidFit) -> str | None:
    """Why a fitted cuboid is no building the networks were trained on, or None: a twobox that is a
    box with a seam or with a sliver, which the box class says in fewer parameters, whatever a few
    pixels of IoU say (an occluder's notch, contour noise, a neighbour's corner, a roof's storey)."""
    if fit.shape != "twobox":
        return None
    ratios = get_shape(fit.shape).ratio_vector(fit.ratios)  # right d/h, w/h, left d/h, w/h: d/h_left over d/h_right
    heights = ratios[0] / ratios[2]  # the LEFT part's height over the RIGHT's
    return seam(heights) or sliver(ratios[1], ratios[3] * heights)


def seam(heights: float) -> str | None:
    """Why a twobox whose parts' heights are in this ratio is a box with a seam (nearly equally high), or None."""
    lower = min(heights, 1 / heights)
    if lower < SEAM_HEIGHT_RATIO:
        return None
    return f"its two parts' heights differ by {100 * (1 - lower):.0f}% (< {100 * (1 - SEAM_HEIGHT_RATIO):.0f}%): a box with a seam"


def sliver(right_width: float, left_width: float) -> str | None:
    """Why a twobox whose parts are this wide (in one unit) is a box with a sliver beside it, or None."""
    share = min(right_width, left_width) / (right_width + left_width)
    if not share < SLIVER_WIDTH_SHARE:  # a width of no size or NaN is impossible's to say
        return None
    return (f"its narrower part is {100 * share:.0f}% of its width (< {100 * SLIVER_WIDTH_SHARE:.0f}%): a box with a sliver "
            f"beside it (a neighbour's corner, a chimney)")


def impossible(fit: CuboidFit) -> str | None:
    """Why a fitted cuboid is no building at all, or None: a part of no width or depth (a twobox's
    split outside its width), or a corner at or behind the camera (the camera inside or behind
    the box). The plausible camera's bounds keep a fit from these, but they are soft: a fit
    that runs away on a mask it cannot explain can still end there (1 of 1,200 generated
    masks, BENCHMARKS.md, "Targets")."""
    ratios = get_shape(fit.shape).ratio_vector(fit.ratios)
    if (ratios <= 0).any():
        return f"a part's ratio is {ratios.min():.3g}: a part of no width or depth"
    if (nearest := fit.camera.nearest_depth()) <= 0:
        return f"a corner lies at or behind the camera (depth {nearest:.3g} of the centre's): the camera is inside or behind it"
    return None


def plausible(fit: CuboidFit) -> bool:
    """Whether a class's fitted cuboid is neither impossible nor implausible: where the shape classifier
    called that class, `choose_cuboid` takes it whatever the others explain."""
    return impossible(fit) is None and implausible(fit) is None


def choose_cuboid(candidates: list[Candidate], cuboids: dict[str, FittedCuboid],
                  called: str | None = None) -> tuple[Candidate, list[str]]:
    """The candidate whose fitted cuboid explains the input best (its IoU, richer classes by
    CUBOID_MARGIN) among the plausible ones, or the class `called` by the shape classifier where it is
    among them (a rough mask: `shape_call`), a warning for each better-explaining class set aside
    as implausible or impossible, and one where even the chosen one is impossible (a forced shape)."""
    judged = [replace(c, confidence=cuboids[c.shape].fit.iou) for c in candidates]
    broken = {c.shape: impossible(cuboids[c.shape].fit) for c in judged}
    reasons = {c.shape: broken[c.shape] or implausible(cuboids[c.shape].fit) for c in judged}
    possible = [c for c in judged if broken[c.shape] is None] or judged
    plausible = [c for c in possible if reasons[c.shape] is None] or possible  # none plausible: judge all alike
    best = next((c for c in plausible if c.shape == called), None) or choose(plausible, margin=CUBOID_MARGIN)
    warnings = [f"the {c.shape} cuboid explained the input better (IoU {c.confidence:.3f} against {best.confidence:.3f}) "
                f"but was set aside: {reasons[c.shape]}"
                for c in judged if c not in plausible and c.confidence > best.confidence + CUBOID_MARGIN]
    if called is not None and called != best.shape and called in reasons:
        warnings.append(f"the shape classifier called the mask {called}, but the {called} cuboid was set aside: "
                        f"{reasons[called]}")
    if broken[best.shape] is not None:
        warnings.append(f"the {best.shape} cuboid is no building: {broken[best.shape]}; its 3D answer is not to be trusted")
    return best, warnings


def stopped_short(cuboids: dict[str, FittedCuboid], chosen: str, mask: np.ndarray) -> float | None:
    """The IoU the chosen class's cuboid should reach on a clean mask (`mask_fit.polygonal`) and did
    not, or None: `mask_fit.RESTART_IOU` (a clean generated mask has a cuboid of IoU about 1), or a
    set-aside class's that explains the mask better by CUBOID_MARGIN (a clean box mask's box a little
    short, and its twobox, a box with a seam, past it: a warning). The classes not chosen are left
    as they are: one that cannot explain the mask (a box on a twobox mask) stops short every time,
    and restarting every class that did cost a tenth of the record (40 masks, bench_infer's)."""
    iou = cuboids[chosen].fit.iou
    reach = max([mask_fit.RESTART_IOU] + [c.fit.iou for c in cuboids.values() if c.fit.iou > iou + CUBOID_MARGIN])
    return reach if iou < reach and polygonal(mask) else None


def astray(cuboids: dict[str, FittedCuboid], chosen: str, mask: np.ndarray) -> list[str]:
    """The classes whose cuboid a given camera may have led astray (`Fitter.freed` fits them again): any
    that is impossible (a corner at or behind the camera), and, where the chosen one is still short of a
    clean mask's silhouette after its restarts (`stopped_short`), every one that leaves more than
    1 - ASTRAY_IOU of it unexplained (short, not astray, is every 64 px fit: the pixel steps there)."""
    short = stopped_short(cuboids, chosen, mask) is not None
    return [shape for shape, cuboid in cuboids.items()
            if impossible(cuboid.fit) is not None or short and cuboid.fit.iou < ASTRAY_IOU]


def heatmap_peaks(heatmaps: np.ndarray) -> np.ndarray:
    """(N, S, S) -> (N,) each map's maximum in [0, 1]: S's confidence in its corner (codec.peak_scores)."""
    return np.clip(heatmaps.reshape(len(heatmaps), -1).max(1).astype(np.float64), 0.0, 1.0)


def corner_scores(fit: CuboidFit, sdf: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """(N,) in [0, 1]: a corner the fitted outline shows scores by how close it lies to the input's
    outline (an occluder that removed it lowers it); a hidden one keeps its heat map's peak, the
    only evidence there is for it."""
    distance = np.abs(bilinear(sdf, fit.keypoints))  # sdf: the input's signed distance to its outline
    seen = np.exp(-0.5 * (distance / CORNER_SCORE_PX) ** 2)
    return np.where(fit.on_outline, seen, peaks)


def check_finite(fit: CuboidFit) -> None:
    """NonFiniteCuboid naming the first number of the fit that is NaN or Infinity (focal length
    excepted: infinite is weak perspective, written as null)."""
    numbers = {"keypoints": fit.keypoints, "ratios": get_shape(fit.shape).ratio_vector(fit.ratios),
               "yaw/pitch/roll": [fit.yaw_deg, fit.pitch_deg, fit.roll_deg], "principal point": fit.principal_px,
               "IoU": [fit.iou], "outline residual": [fit.residual_px]}
    for name, values in numbers.items():
        if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
            raise NonFiniteCuboid(f"the {fit.shape} cuboid fit's {name} is not finite (NaN or Infinity): no fit")
    if math.isnan(fit.focal_px):
        raise NonFiniteCuboid(f"the {fit.shape} cuboid fit's focal length is NaN: no fit")
