"""Does the trust signal mean something? Warning rates and AUROC per scene, flag rates per kind of silhouette.

Fits --samples generated noisy masks a (scene, size) spool (`paper-clean`, `paper`, `street`, every
scene `cuboidgen run --scene` offers; 64, 128 and 256 px; box and twobox mixed) through `infer`
(`Fitter.outcomes`, both shipped models, the cuboid fit), with the camera free and with each mask's
true camera given, and keeps each record's trust signs (`cuboidtrain.fit.trust.SIGNS`), its mean
corner error in 256 px units (infinite where the shape class chosen is not the truth's) and its
error bars' z-scores. Two seed sets: `fit` (the trust model's and the size inflation's data) and
`measure` (the figures reported), never the same masks.

It also makes silhouettes that are no whole box or twobox from the `measure` masks: cut by the
image's border, two or three buildings merged into one region (side by side or overlapping),
random blobs; and reports how often each is flagged (`trust.FLAGS`), beside whole generated buildings.

    .venv/bin/python benchmarks/calibration/bench_trust.py --sets fit --rows fit.json          # two processes,
    .venv/bin/python benchmarks/calibration/bench_trust.py --sets measure --rows measure.json  # one core each
    .venv/bin/python benchmarks/calibration/bench_trust.py --from-rows fit.json measure.json [--fit]  # or measure.json alone

`--fit` fits the error bars' size scaling (`uncertainty.SIZE_INFLATION`), then the trust model
(`trust.MEANS`, `SCALES`, `WEIGHTS`, `INTERCEPT`) and its warnings' limits (`trust.LIMITS`,
`LOW_SCORE`, `CLEAN_OUTLINE`, `LOW_SCORE_CLEAN`: each scene's good fits warned at most `GOOD_WARNED`)
on the `fit` set, prints them to paste and uses them for the tables; without it the
tables are the constants in the code's. The tables are always the `measure` set's: the error bars'
coverage (within 1 / 2 sd per quantity and size), the warning rates and AUROC per scene, and the
flag rates per kind of silhouette.
"""
from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parent.parent / "accuracy")]
from bench_accuracy import SETS, fit_records, spool_for, with_cameras, write_masks  # noqa: E402
from bench_coverage import miss  # noqa: E402

from cuboidtrain.fit import trust  # noqa: E402
from cuboidtrain.fit.fitter import Fitter  # noqa: E402
from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.geometry.accuracy import against_truth  # noqa: E402
from cuboidtrain.geometry.uncertainty import SIZE_INFLATION, SIZE_REFERENCE_PX, inflation  # noqa: E402

SIZES = (64, 128, 256)
PATHS = ("cuboid", "cuboid_camera_given")
SEED_SETS = {"fit": 300, "measure": 400}  # + 10 x the scene's index + the size's index: no spool shared
GOOD_FIT_PX = 3.0  # the trust model's "good fit": mean corner error under this, 256 px units
# Signs the score does not weigh: beside their correlated twins (the mean corner move, the unexplained
# share) their weights came out the wrong way round (a larger miss or move scoring higher), which no
# one could read as an explanation; the warnings and the record still show them.
UNWEIGHED = ("corners_moved_max", "silhouette_miss")
KINDS = ("whole", "border-cut", "merged-2", "merged-3", "blob")


def collect(args) -> list[dict]:
    """One row a fitted record (`record_row`); `kind` rows for the made silhouettes."""
    fitter = Fitter.from_shipped(FitOptions(device="cpu", cuboid=True))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        chosen = {group: base for group, base in SEED_SETS.items() if group in args.sets}
        for (group, base), (s, scene), (z, size) in itertools.product(chosen.items(), enumerate(SETS), enumerate(SIZES)):
            spool = spool_for(args.spools, "mix", scene, args.samples, size=size, seed=base + 10 * s + z)
            files, truths = write_masks(spool, args.samples, Path(tmp))
            for path in PATHS:
                options = with_cameras(fitter.options, path, files, truths)
                records, fits = fit_records(Fitter(fitter.models, options), files)
                for index, (record, fit, truth) in enumerate(zip(records, fits, truths)):
                    rows.append(record_row(record, fit, truth, size) | {"set": group, "scene": scene, "size": size,
                                                                        "path": path, "index": index, "kind": "whole"})
            if group == "measure" and size == 256:
                rows += made_rows(fitter, files, Path(tmp), scene, np.random.default_rng(7 + s))
            print(f"{group} {scene} {size} px: {len(rows)} rows", file=sys.stderr)
            if args.rows:  # what is done so far survives a crash
                args.rows.write_text(json.dumps(rows))
    return rows


def record_row(record: dict, fit, truth, size: int) -> dict:
    """A record's trust, corner error (256 px units; inf: the wrong shape class) and error bars' z-scores."""
    if record["error"] is not None or fit.trust is None:
        return {"failed": True}
    row = {"failed": False, "shape": truth.shape.name, "chosen": record["shape"], "signs": fit.trust.signs,
           "score": fit.trust.score, "codes": [w["code"] for w in record["trust"]["warnings"]]}
    if record["shape"] != truth.shape.name:
        return row | {"error": math.inf}
    keypoints = np.asarray(record["keypoints"])
    row["error"] = float(np.linalg.norm(keypoints - truth.keypoints, axis=1).mean()) * 256 / size
    spread = fit.cuboid.fit.spread
    if spread is not None and truth.camera is not None:
        z = against_truth(keypoints, record["ratios"], truth, fit.cuboid.fit.camera, spread).z_scores
        kinds = ["ratio"] * len(spread.ratios) + ["yaw"] + (["focal"] if spread.focal_px is not None else [])
        row["z"] = [[kind, float(v)] for kind, v in zip(kinds, z)]
        given, px = "focal_px" in fit.cuboid.given, 2 ** fit.trust.signs["mask_px"]
        row["inflation"] = {kind: inflation(given, kind, px) for kind in set(kinds)}  # what z_rows undoes
    return row


def made_rows(fitter: Fitter, files: list[str], folder: Path, scene: str, rng: np.random.Generator) -> list[dict]:
    """Silhouettes that are no whole building, made from the generated masks `files`, fitted free."""
    masks = [cv2.imread(f, cv2.IMREAD_GRAYSCALE) > 127 for f in files]
    made = {kind: [make(kind, masks, rng) for _ in range(len(masks))] for kind in KINDS[1:]}
    rows = []
    for kind, images in made.items():
        paths = []
        for k, image in enumerate(images):
            paths.append(str(folder / f"made-{scene}-{kind}-{k:04d}.png"))
            cv2.imwrite(paths[-1], image.astype(np.uint8) * 255)
        records, fits = fit_records(fitter, paths)
        for k, (record, fit) in enumerate(zip(records, fits)):
            trust = {} if fit is None or fit.trust is None else {
                "signs": fit.trust.signs, "score": fit.trust.score, "codes": [w["code"] for w in record["trust"]["warnings"]],
                "inflation": {"ratio": inflation(False, "ratio", 2 ** fit.trust.signs["mask_px"])}}
            rows.append({"set": "measure", "scene": scene, "size": 256, "path": "cuboid", "index": k, "kind": kind,
                         "failed": not trust} | trust)
    return rows


def make(kind: str, masks: list[np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """One made 256 px silhouette of `kind` from random generated masks."""
    pick = [masks[i] for i in rng.choice(len(masks), size=3, replace=False)]
    if kind == "border-cut":
        return cut_by_border(pick[0], rng)
    if kind in ("merged-2", "merged-3"):
        return merged(pick[: int(kind[-1])], rng)
    return blob(pick[0].shape, rng)


def cut_by_border(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The mask shifted so that 25-60% of its bounding box lies beyond one or two image edges."""
    x, y, w, h = cv2.boundingRect(mask.astype(np.uint8))
    height, width = mask.shape
    dx = dy = 0
    sides = rng.choice(4, size=rng.integers(1, 3), replace=False)
    for side in sides:
        cut = rng.uniform(0.25, 0.6)
        if side == 0:
            dx = -int(x + cut * w)
        elif side == 1:
            dx = int(width - x - (1 - cut) * w)
        elif side == 2:
            dy = -int(y + cut * h)
        else:
            dy = int(height - y - (1 - cut) * h)
    moved = np.zeros_like(mask)
    src = mask[max(0, -dy): height - max(0, dy), max(0, -dx): width - max(0, dx)]
    moved[max(0, dy): max(0, dy) + src.shape[0], max(0, dx): max(0, dx) + src.shape[1]] = src
    return moved if moved.sum() >= 200 else cut_by_border(mask, rng)


def merged(masks: list[np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """Buildings side by side in one region: each cropped to its box, scaled to 60-100% of the first's
    height, bottoms near one line, each overlapping the last by 0-40% of its width; framed in 256 px."""
    crops = [m[y: y + h, x: x + w] for m in masks for x, y, w, h in [cv2.boundingRect(m.astype(np.uint8))]]
    base = crops[0].shape[0]
    parts = []
    for k, crop in enumerate(crops):
        scale = 1.0 if k == 0 else rng.uniform(0.6, 1.0) * base / crop.shape[0]
        size = (max(int(crop.shape[1] * scale), 4), max(int(crop.shape[0] * scale), 4))
        parts.append(cv2.resize(crop.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0)
    width = sum(p.shape[1] for p in parts)
    canvas = np.zeros((2 * base, 2 * width), bool)
    left = width // 2  # room on the left: a wide part may overlap past the first's start
    for k, part in enumerate(parts):
        if k:
            left -= int(rng.uniform(0.0, 0.4) * part.shape[1]) + 1
        bottom = int(1.5 * base) + int(rng.integers(-base // 20 - 1, base // 20 + 1))
        canvas[bottom - part.shape[0]: bottom, left: left + part.shape[1]] |= part
        left += part.shape[1]
    x, y, w, h = cv2.boundingRect(canvas.astype(np.uint8))
    return framed(canvas[y: y + h, x: x + w], masks[0].shape[0])


def blob(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A random smooth region: smoothed noise, scaled up smoothly and thresholded, its largest piece, framed."""
    noise = cv2.resize(cv2.GaussianBlur(rng.normal(size=(64, 64)), (0, 0), rng.uniform(4, 9)), shape[::-1],
                       interpolation=cv2.INTER_CUBIC)
    region = noise > np.quantile(noise, rng.uniform(0.5, 0.8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(region.astype(np.uint8))
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    piece = labels == largest
    x, y, w, h = cv2.boundingRect(piece.astype(np.uint8))
    return framed(piece[y: y + h, x: x + w], shape[0])


def framed(piece: np.ndarray, side: int) -> np.ndarray:
    """`piece` scaled to fit 80% of a `side` px square, centred in it."""
    scale = 0.8 * side / max(piece.shape)
    w, h = max(int(piece.shape[1] * scale), 2), max(int(piece.shape[0] * scale), 2)
    scaled = cv2.resize(piece.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    out = np.zeros((side, side), bool)
    top, left = (side - h) // 2, (side - w) // 2
    out[top: top + h, left: left + w] = scaled
    return out


def auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """The area under the ROC curve of `scores` for telling the `positive` rows from the others: the
    chance that a random positive scores above a random negative (ties count half), by ranks."""
    scores, positive = np.asarray(scores, dtype=np.float64), np.asarray(positive, dtype=bool)
    count, other = int(positive.sum()), int((~positive).sum())
    if not count or not other:
        return math.nan
    order = np.argsort(scores, kind="mergesort")
    ranks = np.empty(len(scores))
    ranks[order] = np.arange(1, len(scores) + 1)
    for value in np.unique(scores):  # ties: their mean rank
        tied = scores == value
        ranks[tied] = ranks[tied].mean()
    return float((ranks[positive].sum() - count * (count + 1) / 2) / (count * other))


def logistic(x: np.ndarray, y: np.ndarray, ridge: float = 1.0, steps: int = 50) -> np.ndarray:
    """Weights (intercept first) of P(y | x) = 1 / (1 + exp(-w . (1, x))), by Newton's method on the
    log likelihood with a ridge penalty on the non-intercept weights (x standardised)."""
    design = np.column_stack([np.ones(len(x)), x])
    w = np.zeros(design.shape[1])
    penalty = ridge * np.diag([0.0] + [1.0] * x.shape[1])
    for _ in range(steps):
        p = 1 / (1 + np.exp(-np.clip(design @ w, -40, 40)))
        gradient = design.T @ (y - p) - penalty @ w
        hessian = design.T @ (design * (p * (1 - p))[:, None]) + penalty
        w = w + np.linalg.solve(hessian, gradient)
    return w


def whole(rows: list[dict], group: str) -> list[dict]:
    return [r for r in rows if r["kind"] == "whole" and r["set"] == group and not r["failed"]]


def signs_now(row: dict) -> dict:
    """A row's signs under today's size inflation: its `ratio_sd` was read under the one it was fitted with."""
    given, px = row["path"] == "cuboid_camera_given", 2 ** row["signs"]["mask_px"]
    then = row.get("inflation", {}).get("ratio", 1.0)
    # Rows collected before the roof's notches were read carry none: counted as no notch (the made
    # masks' counts are bench_notches.py's, which reads the masks again).
    return {"roof_notches": 0.0} | row["signs"] | {"ratio_sd": row["signs"]["ratio_sd"] + math.log(inflation(given, "ratio", px) / then)}


def sign_matrix(rows: list[dict]) -> np.ndarray:
    return np.array([[signs_now(r)[name] for name in trust.SIGNS] for r in rows])


def fit_trust(rows: list[dict]) -> str:
    """The trust model fitted on the `fit` set's whole buildings, as trust.py's constants."""
    fitting = whole(rows, "fit")
    x = sign_matrix(fitting)
    good = np.array([r["error"] < GOOD_FIT_PX for r in fitting], dtype=float)
    means, scales = x.mean(0), x.std(0)
    scales[scales < 1e-6] = 1.0  # a sign constant on whole buildings (the border cut: none is cut) weighs 0
    standard = (x - means) / scales
    standard[:, [trust.SIGNS.index(name) for name in UNWEIGHED]] = 0.0  # weighs 0 (ridge)
    w = logistic(standard, good)
    names = ", ".join(trust.SIGNS)

    def tuple_of(values) -> str:
        return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"

    # The tables below are then the fitted model's: trust.py's constants replaced in this process only.
    trust.MEANS, trust.SCALES, trust.WEIGHTS, trust.INTERCEPT = tuple(means), tuple(scales), tuple(w[1:]), float(w[0])
    return (f"# {len(fitting)} records, {int(good.sum())} good; signs: {names}\n"
            f"MEANS = {tuple_of(means)}\nSCALES = {tuple_of(scales)}\nWEIGHTS = {tuple_of(w[1:])}\n"
            f"INTERCEPT = {w[0]:.4g}")


BELOW = ("heatmap_peak", "shape_margin", "mask_px")  # the signs whose warning is raised below its limit
FLAG_SIGNS = ("unexplained", "outline_rms", "border_cut")  # a silhouette that is no whole building
WHOLE_SHARE = 0.99  # a flag's limit: the share of every whole building on its safe side
GOOD_WARNED = 0.13  # the most of any one scene's good fits (< 3 px) that may carry a warning on the fit set
# Each scene's, not the pooled share: the clean scene's good fits, 55% of the pooled ones and seldom
# warned, hid the noisy scenes' (warned 21% under a pooled 12%). 0.13 leaves room under the issue's
# 15% for the measure seeds' draw (0.14 met it on them with no point to spare).


def fit_limits(rows: list[dict]) -> str:
    """Each warning's limit (`trust.LIMITS`) and the low scores' on the `fit` set's whole buildings:
    a flag's at WHOLE_SHARE of every whole building, the others' at a share of the good fits (< 3 px),
    the low score on a grid: the pair that warns the most of the worst fifth by corner error (every
    scene pooled) while warning at most GOOD_WARNED of each scene's good fits; then a clean outline's
    (`CLEAN_OUTLINE`, `LOW_SCORE_CLEAN`) as the pair that warns the most of each scene's worst fifth
    on average within the same bound (the pooled worst fifth holds few of the clean scene's). The
    scene picks the limits here only: at inference every fit is held to the same ones."""
    fitting = [r | {"now": signs_now(r)} for r in whole(rows, "fit")]
    good = [r for r in fitting if r["error"] < 3]
    worst = [r for r in fitting if r["error"] >= np.quantile([q["error"] for q in fitting], 0.8)]
    names = sorted({r["scene"] for r in fitting})
    scenes = [[r for r in good if r["scene"] == scene] for scene in names]
    worst_of = [[r for r in fitting if r["scene"] == scene and r["error"] >= np.quantile(
        [q["error"] for q in fitting if q["scene"] == scene], 0.8)] for scene in names]

    def warned(groups: list[list[dict]]) -> list[float]:
        return [float(np.mean([bool(trust.judge(r["now"]).warnings) for r in group])) for group in groups]

    best = None
    trust.LOW_SCORE_CLEAN = 0.0  # the clean outline's low score after the others
    for share, low in itertools.product((0.95, 0.96, 0.97, 0.98, 0.99, 0.995, 0.998), np.linspace(0, 0.3, 61)):
        limits = {}
        for name in trust.LIMITS:
            values = np.array([r["now"][name] for r in (fitting if name in FLAG_SIGNS else good)])
            q = WHOLE_SHARE if name in FLAG_SIGNS else share
            limits[name] = float(np.quantile(values, 1 - q if name in BELOW else q))
        limits["border_cut"] = max(limits["border_cut"], 0.05)  # a few px on the edge is no cut building
        trust.LIMITS, trust.LOW_SCORE = limits, float(low)
        shares = warned([worst, *scenes])
        if max(shares[1:]) <= GOOD_WARNED and (best is None or shares[0] > best[0]):
            best = (shares[0], max(shares[1:]), limits, trust.LOW_SCORE)
    if best is None:
        raise SystemExit(f"no limits warn at most {GOOD_WARNED:.0%} of every scene's good fits: the flags alone warn more")
    trust.LIMITS, trust.LOW_SCORE = best[2], best[3]  # as fit_trust's: this process only
    clean = (0.0, trust.CLEAN_OUTLINE, 0.0)
    for rms, low in itertools.product((0.3, 0.4, 0.5, 0.6), np.linspace(best[3], 0.6, 50)):
        trust.CLEAN_OUTLINE, trust.LOW_SCORE_CLEAN = float(rms), float(low)
        if max(warned(scenes)) <= GOOD_WARNED and np.mean(warned(worst_of)) > clean[0]:
            clean = (float(np.mean(warned(worst_of))), trust.CLEAN_OUTLINE, trust.LOW_SCORE_CLEAN)
    trust.CLEAN_OUTLINE, trust.LOW_SCORE_CLEAN = clean[1:]
    return (f"LIMITS = {{{', '.join(f'{k!r}: {v:.3g}' for k, v in best[2].items())}}}\n"
            f"LOW_SCORE = {best[3]:.3g}  # fit set: worst fifth warned {best[0]:.0%}, a scene's good fits at most {best[1]:.0%}\n"
            f"CLEAN_OUTLINE = {clean[1]:.3g}\nLOW_SCORE_CLEAN = {clean[2]:.3g}  # fit set: a scene's worst fifth "
            f"warned {clean[0]:.0%} on average")


def judged(rows: list[dict]) -> list[dict]:
    """The rows' trust under the constants in the code (the rows keep the signs it reads)."""
    return [r | {"trust": trust.judge(signs_now(r))} for r in rows if not r["failed"]]


def warning_table(rows: list[dict]) -> None:
    """Per scene (and all): the share of the worst fifth by corner error that carries a warning, of
    the fits under 3 px that do, and the AUROC of the score for good fits (< 3 px) against bad (> 10 px)."""
    print(f"{'scene':12s} {'records':>7s} {'worst fifth warned':>18s} {'< 3 px warned':>14s} "
          f"{'AUROC':>6s} {'good / bad':>10s}")
    mine = judged(whole(rows, "measure"))
    for scene in (*SETS, "all"):
        group = [r for r in mine if scene in ("all", r["scene"])]
        if not group:
            continue
        error = np.array([r["error"] for r in group])
        warned = np.array([bool(r["trust"].warnings) for r in group])
        score = np.array([r["trust"].score for r in group])
        worst = error >= np.quantile(error, 0.8)
        good, bad = error < 3, error > 10
        both = good | bad
        print(f"{scene:12s} {len(group):7d} {warned[worst].mean():18.0%} {warned[good].mean():14.0%} "
              f"{auroc(score[both], good[both]):6.3f} {f'{good.sum()} / {bad.sum()}':>10s}")


def flag_table(rows: list[dict]) -> None:
    """Per kind of silhouette (whole buildings: 256 px, camera free): the share flagged (any warning),
    the share whose warnings include a FLAGS one (no whole box or twobox), the most common codes."""
    print(f"{'kind':12s} {'masks':>6s} {'flagged':>8s} {'not-a-box / border-cut':>23s}  most common")
    mine = judged([r for r in rows if r["set"] == "measure" and (r["kind"] != "whole" or r["path"] == "cuboid")
                   and (r["kind"] != "whole" or r["size"] == 256)])
    groups = {kind: [r for r in mine if r["kind"] == kind] for kind in KINDS}
    groups["whole < 3 px"] = [r for r in groups["whole"] if r["error"] < 3]  # a flag there is a false one
    for kind, group in groups.items():
        codes = [[w.code for w in r["trust"].warnings] for r in group]
        named = np.mean([bool(set(c) & set(trust.FLAGS)) for c in codes])
        counts = sorted({c: sum(c in cs for cs in codes) for c in set().union(*codes)}.items(), key=lambda kv: -kv[1])
        print(f"{kind:12s} {len(group):6d} {np.mean([bool(c) for c in codes]):8.0%} {named:23.0%}  "
              + ", ".join(f"{c} {n / len(group):.0%}" for c, n in counts[:3]))


def z_rows(rows: list[dict], group: str) -> list[tuple]:
    """(path, kind, image size, silhouette px, z under the calibration without size inflation) of
    every quantity of the group's whole-building rows that have error bars."""
    return [(r["path"], kind, r["size"], 2 ** r["signs"]["mask_px"], z * r.get("inflation", {}).get(kind, 1.0))
            for r in whole(rows, group) for kind, z in r.get("z", [])]


def inflated(z: list[tuple], inflations: dict) -> dict:
    """(path, kind, size) -> (share within 1 sd, within 2 sd, count) with the sds scaled by
    `inflations` ((focal given, kind) -> a, `uncertainty.inflation`'s form)."""
    cells = {}
    for path, kind, size, px, value in z:
        exponent = inflations[path == "cuboid_camera_given", kind]
        cells.setdefault((path, kind, size), []).append(value / max(1.0, SIZE_REFERENCE_PX / px) ** exponent)
    return {key: (float(np.mean(np.array(v) <= 1)), float(np.mean(np.array(v) <= 2)), len(v)) for key, v in cells.items()}


def fit_inflation(rows: list[dict]) -> dict:
    """Each (focal given, kind)'s exponent a, on the `fit` set: the smallest miss of the 64, 128 and
    256 px cells from 70% within 1 sd (+- 5 points) and 92.5% within 2 (`bench_coverage.miss`)."""
    z = z_rows(rows, "fit")
    fitted = {}
    for given, kind in SIZE_INFLATION:
        mine = [q for q in z if (q[0] == "cuboid_camera_given") == given and q[1] == kind]
        scored = [(miss([cell[:2] for cell in inflated(mine, {(given, kind): a}).values()]), float(a))
                  for a in np.linspace(-1, 2, 61)]
        fitted[given, kind] = min(scored)[1]
    return fitted


def coverage_table(rows: list[dict], inflations: dict) -> None:
    """The measure set's error bars: within 1 / 2 sd per path, size and quantity (band 60-80 / 90)."""
    cells = inflated(z_rows(rows, "measure"), inflations)
    print(f"{'path':20s} {'quantity':8s} " + " ".join(f"{f'{size} px':>13s}" for size in SIZES))
    for path, kind in sorted({key[:2] for key in cells}):
        shares = [cells.get((path, kind, size)) for size in SIZES]
        print(f"{path:20s} {kind:8s} " + " ".join(
            f"{f'{100 * c[0]:.0f} / {100 * c[1]:.0f}' + ('' if 0.6 <= c[0] <= 0.8 and c[1] >= 0.9 else '*'):>13s}"
            if c else f"{'-':>13s}" for c in shares))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=100, help="masks a (seed set, scene, size) spool, box and twobox mixed")
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--sets", nargs="+", choices=tuple(SEED_SETS), default=tuple(SEED_SETS), help="the seed sets to fit")
    parser.add_argument("--rows", type=Path, default=None, help="also write every row (JSON)")
    parser.add_argument("--from-rows", type=Path, nargs="+", default=None, help="read the rows instead of fitting")
    parser.add_argument("--fit", action="store_true", help="fit the trust model and the size inflation on the fit set")
    args = parser.parse_args()
    torch.set_num_threads(1)
    logging.disable(logging.WARNING)  # every made mask's warnings: the rows keep them
    rows = [row for path in args.from_rows for row in json.loads(path.read_text())] if args.from_rows else collect(args)
    if args.rows:
        args.rows.write_text(json.dumps(rows))
    sets = {r["set"] for r in rows}
    if "measure" not in sets or args.fit and "fit" not in sets:  # the tables are the measure set's; --fit fits on fit's
        return
    inflations = dict(SIZE_INFLATION)
    if args.fit:
        inflations = fit_inflation(rows)
        SIZE_INFLATION.update(inflations)  # the signs' ratio_sd under the fitted inflation (this process only)
        print("SIZE_INFLATION = {" + ", ".join(f"{key}: {a:.2f}" for key, a in inflations.items()) + "}")
        print(fit_trust(rows))
        print(fit_limits(rows))
    coverage_table(rows, inflations)
    warning_table(rows)
    flag_table(rows)


if __name__ == "__main__":
    main()
