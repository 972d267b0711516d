"""How far to trust a fit: a score and named warnings from what the fit path itself shows.

The record's `confidence` is the fitted silhouette's IoU with the input: it stays high when the
box explains the outline and nothing else agrees (issue 38: a wall at a grazing angle fitted at
0.86 with its networks' corners moved 36 px to reach the box). The trust signal reads the signs
the fit already computes, each named (`SIGNS`):

* `corners_moved`, `corners_moved_max`: how far the networks' corners moved to reach the fitted
  box (mean and largest, in % of the silhouette's size: its bounding box's longer side);
* `heatmap_peak`: the Estimator's heat maps' mean peak (its own confidence in its corners);
* `silhouette_miss`: 1 - the fitted silhouette's IoU with the input;
* `unexplained`: the share of the silhouette's pixels the fitted cuboid's silhouette leaves out (an
  occluder's hole makes the box overhang the mask, which this does not count; a second building
  beside the first is left out);
* `outline_rms`: the outline's rms residual, in % of the silhouette's size;
* `shape_margin`: how much better the chosen class explains the input than the other (IoU);
* `mask_px`: log2 of the silhouette's size in px (small masks show little);
* `hidden_corners`: the share of corners the fitted outline does not show (decided by the networks,
  not the outline);
* `ratio_sd`: log of the widest ratio error bar relative to its ratio;
* `border_cut`: the share of the silhouette's outline on the image's edge;
* `roof_notches`: how many notches open down from the outline's top deeper than ROOF_NOTCH_DEPTH of
  its size (`silhouette.roof_notches`): a box has none, a twobox one at most, a row of houses more.

The score is a logistic regression of "a good fit" (mean corner error under 3 px in 256 px units) on
these signs (standardised), fitted on generated noisy masks (`benchmarks/calibration/bench_trust.py
--fit`, masks of other seeds than those it is measured on); each warning is one sign past a limit
chosen there, or the score under one, with what to do.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cuboidtrain.fit.candidates import Candidate, border_cut
from cuboidtrain.fit.cuboid import FittedCuboid, heatmap_peaks
from cuboidtrain.fit.shape_call import ShapeCall
from cuboidtrain.geometry.camera_params import CuboidFit
from cuboidtrain.geometry.silhouette import extent_px, model_silhouette, roof_notches
from shared.shapes import get_shape

SIGNS = ("corners_moved", "corners_moved_max", "heatmap_peak", "silhouette_miss", "unexplained", "outline_rms",
         "shape_margin", "mask_px", "hidden_corners", "ratio_sd", "border_cut", "roof_notches")

# The logistic model of P(good fit | signs): weights of the standardised signs (mean, sd) and an
# intercept, fitted by benchmarks/calibration/bench_trust.py --fit on 1,798 records of generated noisy
# masks (the `fit` seeds: paper-clean, paper, street; box and twobox mixed; 64, 128 and 256 px; the
# camera free and given), a good fit's mean corner error under 3 px in 256 px units (663 of them).
# The border cut is 0 on every generated mask: it weighs nothing here, and warns below; the largest
# corner move and the IoU weigh nothing either (bench_trust.UNWEIGHED: beside the mean move and the
# unexplained share their weights came out the wrong way round). The roof's notches came after the
# fit (mean 0, scale 1, weight 0): they flag below and weigh nothing until the model is fitted again.
MEANS = (3.253, 7.625, 0.5954, 0.1109, 0.007036, 0.7988, 0.05684, 6.678, 0.3542, -1.381, 0.0, 0.0)
SCALES = (2.555, 5.978, 0.0938, 0.162, 0.008697, 0.5427, 0.06895, 0.8282, 0.09872, 0.6908, 1.0, 1.0)
WEIGHTS = (-0.3395, 0.0, 0.7714, 0.0, -1.103, -0.1885, 0.163, 0.4489, -0.503, -0.7941, 0.0, 0.0)
INTERCEPT = -1.177
UNREAD_MARGIN = MEANS[SIGNS.index("shape_margin")]  # no other class fitted: the sign adds nothing to the score
# "high": a score at least HIGH and no warning; "low": a score under `low_score` (below) or a flag (no
# whole building); "medium" the rest. On the `measure` seeds: high 34% of the records (73% of them
# under 3 px, 2% over 10), medium 32% (24%, 16%), low 34% (5%, 47%).
HIGH = 0.5


@dataclass(frozen=True)
class NamedWarning:
    """One named reason to doubt a fit: a short code, what was seen, and what to do."""

    code: str
    message: str
    action: str

    def record(self) -> dict:
        return {"code": self.code, "message": self.message, "action": self.action}


@dataclass(frozen=True)
class Trust:
    """A fit's trust: a score in [0, 1] (P(good fit) under the model), its level, the signs it read, why."""

    score: float
    level: str  # "high", "medium" or "low" (`level`)
    signs: dict[str, float]
    warnings: tuple[NamedWarning, ...]

    def lines(self) -> tuple[str, ...]:
        """The warnings as the record's `warnings` entries: "code: what was seen; what to do"."""
        return tuple(f"{w.code}: {w.message}; {w.action}" for w in self.warnings)

    def record(self) -> dict:
        """The infer record's `trust` object (docs/contract.md, "The trust object")."""
        return {"level": self.level, "score": round(self.score, 4),
                "warnings": [w.record() for w in self.warnings],
                "signs": {name: round(value, 4) for name, value in self.signs.items()}}


def signs(candidate: Candidate, cuboid: FittedCuboid, mask: np.ndarray, other_ious: list[float] | None) -> dict[str, float]:
    """The named signs (`SIGNS`) of one fitted component: `candidate` the chosen shape class's, `cuboid`
    its fit, `mask` (H, W) bool the component in the input's pixels, `other_ious` the other classes'
    fitted IoUs; None where no other class was fitted because the shape classifier's sure call chose this
    one alone (`Fitter.first_cuboids`): the margin is then read at the model's mean, no evidence either way."""
    fit = cuboid.fit
    size = extent_px(mask)
    network = candidate.framing.to_input(candidate.keypoints)[fit.camera.naming()]  # in the fit's corner order
    moved = np.linalg.norm(network - fit.keypoints, axis=1) / size * 100
    relative = np.asarray(fit.spread.ratios) / _ratios(cuboid) if fit.spread is not None else np.array([1.0])
    iou = fit.iou if fit.iou is not None else 0.0
    return {"corners_moved": float(moved.mean()), "corners_moved_max": float(moved.max()),
            "heatmap_peak": float(heatmap_peaks(candidate.heatmaps).mean()), "silhouette_miss": 1.0 - iou,
            "unexplained": unexplained(fit, mask),
            "outline_rms": fit.residual_px / size * 100,
            "shape_margin": UNREAD_MARGIN if other_ious is None else iou - max(other_ious, default=0.0),
            "mask_px": math.log2(size),
            "hidden_corners": float(1.0 - np.mean(fit.on_outline)),
            "ratio_sd": math.log(max(float(np.max(relative)), 1e-6)), "border_cut": border_cut(mask),
            "roof_notches": float(roof_notches(mask, ROOF_NOTCH_DEPTH, size))}


def unexplained(fit: CuboidFit, mask: np.ndarray) -> float:
    """The share of the silhouette's pixels the fit's silhouette leaves out: the one `described` counted
    with its IoU (a mask fit's), else counted here."""
    if fit.unexplained is not None:
        return fit.unexplained
    return float((mask & ~model_silhouette(fit.shape, fit.keypoints, mask.shape)).sum() / max(mask.sum(), 1))


def _ratios(cuboid: FittedCuboid) -> np.ndarray:
    return np.maximum(np.abs(get_shape(cuboid.fit.shape).ratio_vector(cuboid.fit.ratios)), 1e-9)


def score(values: dict[str, float]) -> float:
    """P(good fit | signs) under the stored logistic model, in [0, 1]."""
    x = (np.array([values[name] for name in SIGNS]) - np.array(MEANS)) / np.array(SCALES)
    return float(1.0 / (1.0 + math.exp(-float(np.clip(INTERCEPT + x @ np.array(WEIGHTS), -40, 40)))))


def level(value: float, low: float, found: list[NamedWarning]) -> str:
    """"high", "medium" or "low" for a score, the score under which its signs are doubted (`low_score`)
    and its warnings (HIGH, FLAGS)."""
    if value < low or any(w.code in FLAGS for w in found):
        return "low"
    return "high" if value >= HIGH and not found else "medium"


def judge(values: dict[str, float], call: ShapeCall | None = None) -> Trust:
    """The trust of a fit with these signs (and `call`, where the shape classifier called the class the
    fit has: then the shape is no guess, whatever the IoU's margin): its score, level and warnings."""
    value = score(values)
    found = warnings(values, value, call)
    return Trust(value, level(value, low_score(values), found), dict(values), tuple(found))


# Each warning: the sign it reads and the limit past which it is raised (above it; `heatmap_peak`,
# `shape_margin`, `mask_px` below it). Chosen on the same records as the model
# (bench_trust.fit_limits): a flag's (no whole building: `unexplained`, `outline_rms`, `border_cut`)
# where 99% of whole generated buildings lie on its safe side; the others' (at the 99.8th percentile
# of the good fits, < 3 px) and the low score's as the pair that warned the most of the worst fifth
# by corner error (71%) while warning at most 13% of any one scene's good fits. Held to the pooled
# good fits instead (12%, as before), the noisy scenes' were warned 21% and 24%: the low score
# (0.241 then) fell on noisy outlines' good fits, whose unexplained share and residual score low.
LIMITS = {"corners_moved": 9.76, "heatmap_peak": 0.4, "unexplained": 0.038, "outline_rms": 2.41,
          "shape_margin": -0.0167, "mask_px": 5.52, "ratio_sd": -0.242, "border_cut": 0.05}
LOW_SCORE = 0.11  # below it, "low-trust": the signs together say doubt even where none alone does
# On a clean outline (its rms residual under CLEAN_OUTLINE % of the size) the score of a good fit is
# high (the clean scene's median 0.75): a score under LOW_SCORE_CLEAN there is doubt too, mostly a
# hidden corner the networks placed wrong behind a right outline. Chosen as the pair after the
# above that warned the most of each scene's worst fifth on average (69%; 52% without it) within the
# same 13%: on the `measure` seeds it brings the clean scene's worst fifth warned from 8% to 30%.
CLEAN_OUTLINE = 0.6
LOW_SCORE_CLEAN = 0.24


def low_score(values: dict[str, float]) -> float:
    """The score under which these signs earn "low-trust": LOW_SCORE_CLEAN on a clean outline, else LOW_SCORE."""
    return LOW_SCORE_CLEAN if values["outline_rms"] < CLEAN_OUTLINE else LOW_SCORE


# The error bars' size scaling (`uncertainty.inflation`) was fitted and measured on silhouettes of
# 31-231 px (64, 128, 256 px images): below this one, the small-mask warning says they are untested.
SMALLEST_MEASURED_PX = 32.0
# A roof line with ROOF_NOTCHES notches deeper than ROOF_NOTCH_DEPTH of the silhouette's size is no
# box's (none) or twobox's (one at most): `benchmarks/calibration/bench_notches.py` on two seed sets
# of generated noisy masks (every scene, 64-256 px): whole buildings 0-1% (an occluder notches from the
# bottom or side), two merged 8-11%, three 12-17%, blobs 3-6%. Shallower ones (5%) flag 2-3% of whole
# noisy buildings, one notch 26-32%; a row of two houses mostly shows one notch, as a twobox does.
ROOF_NOTCH_DEPTH = 0.08
ROOF_NOTCHES = 2
SHAPE_ACTION = "read `candidates` and `shape_call`; pass --shape box or --shape twobox if you know it"
FLAGS = ("not-a-box", "border-cut")  # the warnings that say a silhouette is no whole box or twobox
NOT_A_BOX_ACTION = "give each building its own mask (split a row of houses), or do not use the 3D answer"


def warnings(values: dict[str, float], value: float, call: ShapeCall | None = None) -> list[NamedWarning]:
    """The named warnings these signs (and their score `value`, and the shape classifier's `call`) earn,
    each with what was seen and what to do."""
    found = []
    if values["border_cut"] > LIMITS["border_cut"]:
        found.append(NamedWarning("border-cut", f"{100 * values['border_cut']:.0f}% of the silhouette's outline lies on the "
                                  f"image's edge: the building is cut by the frame, its hidden corners guessed",
                                  "fit a crop that shows the whole building, or read only its visible corners"))
    if values["unexplained"] > LIMITS["unexplained"] or values["outline_rms"] > LIMITS["outline_rms"]:
        found.append(NamedWarning("not-a-box", f"the fitted cuboid leaves {100 * values['unexplained']:.0f}% of the silhouette "
                                  f"out, with an outline residual of {values['outline_rms']:.1f}% of its size: it is no whole "
                                  f"box or twobox (merged buildings, a fragment, no building)",
                                  NOT_A_BOX_ACTION))
    elif values["roof_notches"] >= ROOF_NOTCHES:
        found.append(NamedWarning("not-a-box", f"the silhouette's roof line has {values['roof_notches']:.0f} notches deeper "
                                  f"than {100 * ROOF_NOTCH_DEPTH:.0f}% of its size, which no box (none) or twobox (one) "
                                  f"shows: merged buildings, or no building", NOT_A_BOX_ACTION))
    if values["corners_moved"] > LIMITS["corners_moved"]:
        found.append(NamedWarning("corners-moved", f"the networks' corners moved {values['corners_moved']:.0f}% of the "
                                  f"silhouette's size on average ({values['corners_moved_max']:.0f}% at most) to reach the "
                                  f"fitted cuboid: the networks and the box disagree",
                                  "check the fit with --explain; give the camera (--focal-px) if it is known"))
    if values["heatmap_peak"] < LIMITS["heatmap_peak"]:
        found.append(NamedWarning("weak-heatmaps", f"the Estimator's heat maps peak at {values['heatmap_peak']:.2f} on average: "
                                  f"it is unsure where the corners are", "check with --explain that the mask is one building "
                                  "seen whole; an unusual view or shape is out of what the networks learnt"))
    # where the shape classifier's sure call chose the class, the IoU's margin is no doubt (`shape_call.SURE`)
    if (call is None or call.shape is None) and values["shape_margin"] < LIMITS["shape_margin"]:
        found.append(NamedWarning("shape-undecided", f"the chosen shape class explains the silhouette by only "
                                  f"{values['shape_margin']:+.3f} IoU against the other: the shape is a guess",
                                  SHAPE_ACTION))
    if values["mask_px"] < LIMITS["mask_px"]:
        untested = ("" if 2 ** values["mask_px"] >= SMALLEST_MEASURED_PX else
                    f"; its error bars are untested below {SMALLEST_MEASURED_PX:.0f} px (measured on silhouettes of 31-231 px)")
        found.append(NamedWarning("small-mask", f"the silhouette is {2 ** values['mask_px']:.0f} px across: its corners "
                                  f"are a few pixels each{untested}", "use a larger crop or a mask at the photo's full resolution"))
    if values["ratio_sd"] > LIMITS["ratio_sd"]:
        found.append(NamedWarning("wide-error-bars", f"a ratio's error bar is {100 * math.exp(values['ratio_sd']):.0f}% of "
                                  f"the ratio: the silhouette hardly fixes the 3D shape",
                                  "give the camera (--focal-px, --camera); read the ratios as a range, not a value"))
    if value < low_score(values) and not found:
        found.append(NamedWarning("low-trust", f"the trust score is {value:.2f}: the signs together say doubt, none alone",
                                  "check the fit with --explain before using it"))
    return found
