"""How far shape selection can go on the evidence the two fitted cuboids and the mask give (issue 37, Must have 6).

`infer` chooses box or twobox by the fitted cuboids' IoU with the input (the twobox by
`fit.cuboid.CUBOID_MARGIN`) and two plausibility gates (`fit.cuboid.implausible`). This asks whether
any rule on richer evidence would do better: per mask, as `infer --cuboid` fits it (both shipped
models, both classes' cuboids), it reads the evidence below, fits a logistic regression of "the true
class is twobox" on the masks of the tuning seeds (`bench_accuracy.py --tuning-seeds`'), and scores it,
at several thresholds, on bench_accuracy's own masks beside the shipped rule:

* `gain`: the twobox's IoU less the box's; `gain_share`: that over what the box leaves (1 - its IoU);
* `narrow_share`, `height_ratio`: the twobox's narrower part over its width, its lower part's height
  over the taller's (the sliver and seam gates' measures, here weighed instead of cut);
* `solidity`: the mask's area over its convex hull's; `network_margin`: the twobox model's keypoint
  confidence less the box model's (`geometry.silhouette.confidence`: `candidates.choose`'s evidence
  without a cuboid);
* `roof_notch`: the deepest notch opening down from the outline's top, a share of its size
  (`geometry.silhouette.roof_notches` counts them past a depth);
* `implausible`: 1 where a gate sets the twobox aside (the rule keeps the gates whatever the regression says).

`--decidable` asks the silhouette instead: each twobox sample's clean mask (its true silhouette,
before occluders, noise and, in `irregular`, the building's deviations) through `infer --cuboid`,
the share called twobox: what evidence the masks had before they were damaged.

`--classifier BOX_SPOOL TWOBOX_SPOOL` asks a network instead of a rule: a small CNN (four strided
blocks, 0.2 M weights) trained for `--classifier-minutes` on one thread to call the class from the
framed noisy mask alone (64 px, grey, as the shipped models read it; flipped at random), scored on
the same masks, alone and as one more piece of evidence (its logit) in the regression. The spools
below are the 128 px training spools that `SPOOLS=spools-irr SAMPLES=20000 IRREGULAR=20000
recipes/shipped.sh` draws (20,000 `paper`, `street` and `irregular` samples a class).

    .venv/bin/python benchmarks/accuracy/bench_selection.py --samples 200 --tuning-samples 150 --decidable \
        --classifier spools-irr/train-box-128 spools-irr/train-twobox-128 --classifier-minutes 25

`--breakdown` asks only where `infer`'s misses on irregular buildings are: each mask's call beside what
the generator drew for it (a twobox's height ratio, the share occluders hid, each deviation), the % given
their own class by band (`--seed-offset`: 0 bench_accuracy's seeds, 100 its tuning seeds, others fresh):

    .venv/bin/python benchmarks/accuracy/bench_selection.py --breakdown --samples 200 --seed-offset 0
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

import bench_accuracy as ba
from cuboidtrain.fit import fitter as fitter_module
from cuboidtrain.fit.cuboid import implausible, impossible
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.shape_call import classifier_input
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.geometry.silhouette import confidence, extent_px, top_notches
from cuboidtrain.models.checkpoint import load_model
from cuboidtrain.models.zoo import default_checkpoints
from cuboidtrain.train.classifier_training import train_classifier
from shared.sample import decode
from shared.shapes import get_shape
from shared.spool import enumerate_spool, read_sample_bytes

EVIDENCE = ("gain", "gain_share", "narrow_share", "height_ratio", "solidity", "network_margin", "roof_notch", "implausible")
THRESHOLDS = (-0.5, 0.0, 0.5, 1.0)  # on the regression's log-odds: lower calls more masks twobox
SCENES = ("irregular", "street", "paper", "paper-clean")


class Witness:
    """`choose_cuboid` as the Fitter calls it, wrapped to keep the last call's candidates and cuboids (both
    classes' fits, which a record keeps only for the chosen one); the choice itself unchanged."""

    def __init__(self):
        self.chosen, self.last = fitter_module.choose_cuboid, {}

    def __enter__(self) -> "Witness":
        def witnessed(candidates, cuboids, called=None):
            # the networks' own confidence, which `infer --cuboid` no longer computes (the cuboids' IoU judges),
            # and the class the silhouettes alone choose (the shape classifier's call left out)
            self.last = {"networks": {c.shape: confidence(c.shape, c.keypoints, c.framed >= 0.5) for c in candidates},
                         "cuboids": dict(cuboids), "silhouette": self.chosen(candidates, cuboids)[0].shape}
            return self.chosen(candidates, cuboids, called)
        fitter_module.choose_cuboid = witnessed
        return self

    def __exit__(self, *exc) -> None:
        fitter_module.choose_cuboid = self.chosen


def roof_notch(mask: np.ndarray) -> float:
    """The deepest notch opening down from the outline's top (`silhouette.top_notches`), as a share of the
    silhouette's size; 0 where none."""
    return float(top_notches(mask).max(initial=0) / 256 / extent_px(mask))  # OpenCV's depths: 8 fractional bits


def evidence(mask: np.ndarray, seen: dict) -> dict[str, float]:
    box, twobox = seen["cuboids"]["box"].fit, seen["cuboids"]["twobox"].fit
    ratios = get_shape("twobox").ratio_vector(twobox.ratios)  # right d/h, w/h, left d/h, w/h (each over its own h)
    heights = ratios[0] / ratios[2]  # the left part's height over the right's
    right, left = ratios[1], ratios[3] * heights
    hull = cv2.contourArea(cv2.convexHull(cv2.findNonZero(mask.astype(np.uint8))))
    return {"gain": twobox.iou - box.iou, "gain_share": (twobox.iou - box.iou) / max(1 - box.iou, 1e-6),
            "narrow_share": min(right, left) / (right + left), "height_ratio": min(heights, 1 / heights),
            "solidity": float(mask.sum() / max(hull, 1.0)),
            "network_margin": seen["networks"]["twobox"] - seen["networks"]["box"], "roof_notch": roof_notch(mask),
            "implausible": float(implausible(twobox) is not None or impossible(twobox) is not None)}


def scored_samples(root: Path, shape: str, scene: str, samples: int, offset: int = 0):
    """The first `samples` samples of (shape, scene)'s spool of seed SEEDS + `offset` (`ba.spool_for`) that
    `infer` can score: one an occluder hid whole is refused, no choice to score."""
    spool = ba.spool_for(root, shape, scene, samples, seed=ba.SEEDS[shape, scene] + offset)
    for name in enumerate_spool(spool)[:samples]:
        sample = decode(read_sample_bytes(spool, name))
        if sample.noisy.any():
            yield sample


def measured(fitter: Fitter, root: Path, samples: int, tuning: bool) -> list[dict]:
    """Per mask of every scene and class: its true class, `infer`'s choice, its evidence and its
    framed input (`classifier_input`, for --classifier)."""
    rows = []
    for scene in SCENES:
        for shape in ("box", "twobox"):
            for sample in scored_samples(root, shape, scene, samples, ba.TUNING_OFFSET if tuning else 0):
                mask = sample.noisy
                with Witness() as witness:
                    chosen = fitter.fit(mask).shape
                rows.append({"scene": scene, "shape": shape, "chosen": chosen, "silhouette": witness.last["silhouette"],
                             "input": classifier_input(mask)}
                            | evidence(mask, witness.last))
    return rows


def classifier(spools: list[Path], minutes: float, batch: int = 128) -> nn.Module:
    """The shape classifier (`cuboidtrain.train.classifier_training`) trained on a box spool and a twobox spool
    for `minutes`: what `cuboidtrain classifier train` ships, here without its file."""
    trained = train_classifier({"box": spools[0], "twobox": spools[1]}, minutes, batch_size=batch)
    print(f"classifier: {trained.steps} steps of {batch} in {minutes:g} min on {sum(trained.masks.values())} masks "
          f"({trained.hidden} hidden whole, left out)")
    return trained.net


def with_logits(rows: list[dict], net: nn.Module) -> list[dict]:
    with torch.no_grad():
        logits = net(torch.from_numpy(np.stack([r["input"] for r in rows]))[:, None]).tolist()
    return [r | {"classifier": logit} for r, logit in zip(rows, logits)]


def evidence_matrix(rows: list[dict], names: tuple[str, ...]) -> np.ndarray:
    """(masks, names): each mask's evidence, clipped to +-8 (a gain share over a box that explains nearly all)."""
    return np.clip(np.array([[r[k] for k in names] for r in rows]), -8, 8)


def regression(rows: list[dict], names: tuple[str, ...] = EVIDENCE, l2: float = 0.01, steps: int = 4000) -> tuple:
    """The standardised evidence's means, scales and logistic weights (intercept last), by gradient descent."""
    x = evidence_matrix(rows, names)
    y = np.array([r["shape"] == "twobox" for r in rows], float)
    mean, scale = x.mean(0), x.std(0) + 1e-9
    z = np.c_[(x - mean) / scale, np.ones(len(x))]
    weights = np.zeros(z.shape[1])
    for _ in range(steps):
        weights -= 0.5 * (z.T @ (1 / (1 + np.exp(-z @ weights)) - y) / len(y) + l2 * weights)
    return names, mean, scale, weights


def called(rows: list[dict], model, threshold: float) -> list[str]:
    names, mean, scale, weights = model
    x = evidence_matrix(rows, names)
    odds = np.c_[(x - mean) / scale, np.ones(len(x))] @ weights
    return ["twobox" if o > threshold and not r["implausible"] else "box" for o, r in zip(odds, rows)]


def shares(rows: list[dict], calls: list[str]) -> dict[str, float]:
    """scene/shape -> the % of its masks given their own class."""
    out = {}
    for scene in SCENES:
        for shape in ("box", "twobox"):
            own = [c == r["shape"] for r, c in zip(rows, calls) if r["scene"] == scene and r["shape"] == shape]
            if own:
                out[f"{scene}/{shape}"] = round(100 * float(np.mean(own)), 1)
    return out


def decidable(fitter: Fitter, root: Path, samples: int) -> dict[str, float]:
    """scene -> the % of twobox samples whose clean silhouette `infer` calls twobox (tuning seeds)."""
    out = {}
    for scene in SCENES[:3]:
        spool = ba.spool_for(root, "twobox", scene, samples, seed=ba.SEEDS["twobox", scene] + ba.TUNING_OFFSET)
        calls = [fitter.fit(decode(read_sample_bytes(spool, n)).clean).shape for n in enumerate_spool(spool)[:samples]]
        out[scene] = round(100 * calls.count("twobox") / len(calls), 1)
    return out


# --breakdown's bands of what the generator drew: a twobox's lower part's height over the taller's (the
# scene draws 0.35-0.85), and the share of the building's silhouette the occluders hid.
BANDS = {"height_ratio": (0.6, 0.75), "occluded_fraction": (0.1, 0.25)}
DEVIATIONS = ("roof", "chimney", "parapet", "neighbour", "blob", "low_res")


def drawn(params: dict) -> dict:
    """What `--breakdown` reads of a sample's params: its bands' values and the deviations it got."""
    kinds = {d["kind"] for d in params.get("deviations", ())}
    return {name: params.get(name) for name in BANDS} | {kind: kind in kinds for kind in DEVIATIONS}


def irregular_calls(fitter: Fitter, root: Path, samples: int, offset: int) -> list[dict]:
    """Per irregular mask of seeds SEEDS + `offset`: its true class, `infer`'s call, and `drawn` of its params."""
    return [{"shape": shape, "right": fitter.fit(sample.noisy).shape == shape} | drawn(sample.params)
            for shape in ("box", "twobox") for sample in scored_samples(root, shape, "irregular", samples, offset)]


def banded(rows: list[dict]) -> dict[str, dict[str, tuple[float, int]]]:
    """class -> {group: (% given their own class, masks)}: all, each band of BANDS (a value under the band's
    first edge, between them, from the second up; height ratio for twoboxes only), each deviation with and
    without it."""
    def share(group: list[dict]) -> tuple[float, int]:
        return (round(100 * float(np.mean([r["right"] for r in group])), 1) if group else float("nan"), len(group))

    out = {}
    for shape in ("box", "twobox"):
        own = [r for r in rows if r["shape"] == shape]
        groups = {"all": own}
        for name, (low, high) in BANDS.items():
            if own and own[0][name] is not None:
                groups |= {f"{name} < {low:g}": [r for r in own if r[name] < low],
                           f"{name} {low:g}-{high:g}": [r for r in own if low <= r[name] < high],
                           f"{name} >= {high:g}": [r for r in own if r[name] >= high]}
        for kind in DEVIATIONS:
            groups |= {f"{kind}": [r for r in own if r[kind]], f"no {kind}": [r for r in own if not r[kind]]}
        out[shape] = {group: share(members) for group, members in groups.items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=200, help="bench_accuracy's masks a set and class, scored")
    parser.add_argument("--tuning-samples", type=int, default=150, help="masks of the tuning seeds the regression is fitted on")
    parser.add_argument("--spools", type=Path, default=Path("spools"))
    parser.add_argument("--decidable", action="store_true", help="also: twobox samples' clean silhouettes called twobox")
    parser.add_argument("--classifier", nargs=2, type=Path, metavar=("BOX_SPOOL", "TWOBOX_SPOOL"),
                        help="also: a CNN trained on these spools' noisy masks, alone and as evidence")
    parser.add_argument("--classifier-minutes", type=float, default=25.0)
    parser.add_argument("--breakdown", action="store_true", help="only: where infer's irregular misses are, by what was drawn")
    parser.add_argument("--seed-offset", type=int, default=0, help="--breakdown's seeds: bench_accuracy's plus this")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    fitter = Fitter([load_model(p)[0] for p in default_checkpoints(None)], FitOptions(device="cpu", cuboid=True))
    if args.breakdown:
        result = banded(irregular_calls(fitter, args.spools, args.samples, args.seed_offset))
        for shape, groups in result.items():
            print(f"irregular {shape} masks given their own class (%, masks):")
            for group, (percent, masks) in groups.items():
                print(f"{group:>32} {percent:5.1f} {masks:4d}")
        if args.json:
            args.json.write_text(json.dumps(result, indent=1) + "\n")
        return
    tuning = measured(fitter, args.spools, args.tuning_samples, tuning=True)
    scored = measured(fitter, args.spools, args.samples, tuning=False)
    model = regression(tuning)
    result = {"evidence": dict(zip(EVIDENCE, np.round(model[3][:-1], 3).tolist())),
              "shipped": shares(scored, [r["chosen"] for r in scored]),
              "silhouette": shares(scored, [r["silhouette"] for r in scored]),
              "regression": {str(t): shares(scored, called(scored, model, t)) for t in THRESHOLDS},
              "decidable": decidable(fitter, args.spools, args.tuning_samples) if args.decidable else None}
    if args.classifier:
        net = classifier(args.classifier, args.classifier_minutes)
        tuning, scored = with_logits(tuning, net), with_logits(scored, net)
        both = regression(tuning, EVIDENCE + ("classifier",))
        result["classifier"] = shares(scored, ["twobox" if r["classifier"] > 0 else "box" for r in scored])
        result["regression_with_classifier"] = {str(t): shares(scored, called(scored, both, t)) for t in THRESHOLDS}
    print("% of masks given their own class:", " ".join(f"{k}" for k in result["shipped"]))
    print(f"{'shipped (infer)':>26}", " ".join(f"{v:5.1f}" for v in result["shipped"].values()))
    print(f"{'the silhouettes alone':>26}", " ".join(f"{v:5.1f}" for v in result["silhouette"].values()))
    for label, table in [(f"regression > {t}", f) for t, f in result["regression"].items()] + \
            ([("classifier alone", result["classifier"])] if args.classifier else []) + \
            [(f"+ classifier > {t}", f) for t, f in result.get("regression_with_classifier", {}).items()]:
        print(f"{label:>26}", " ".join(f"{v:5.1f}" for v in table.values()))
    print("weights of the standardised evidence:", result["evidence"])
    if result["decidable"]:
        print("twobox samples' clean silhouettes called twobox (%):", result["decidable"])
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
