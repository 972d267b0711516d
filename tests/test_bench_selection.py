"""bench_selection's evidence (issue 37, Must have 6): the roof's notch, the regression, the witness of the choice."""
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cuboidtrain.fit import fitter as fitter_module
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy"))
from bench_selection import (EVIDENCE, Witness, banded, called, drawn, evidence, irregular_calls, regression,  # noqa: E402
                             roof_notch, shares)


def polygon_mask(points, size: int = 128) -> np.ndarray:
    mask = np.zeros((size, size), np.uint8)
    cv2.fillPoly(mask, [np.asarray(points, np.int32)], 1)
    return mask.astype(bool)


def test_a_convex_silhouette_has_no_roof_notch_and_a_step_has_one_as_deep_as_it():
    # a convex quadrilateral's slanted top edge leaves only its rasterised staircase: under a pixel of its 95 px
    assert roof_notch(polygon_mask([(20, 30), (100, 20), (110, 100), (15, 105)])) < 1 / 95
    # a twobox's silhouette: the lower part's roof 40 px below the taller's; size 100 px (its width)
    step = roof_notch(polygon_mask([(10, 10), (50, 10), (50, 50), (110, 50), (110, 110), (10, 110)]))
    # its depth: the inner corner (50, 50)'s distance to the hull edge (50, 10)-(110, 50) over it, 2400 / 72.1 px
    assert step == pytest.approx(2400 / np.hypot(60, 40) / 101, abs=0.01)
    # an occluder's notch from the bottom is not the roof's
    assert roof_notch(polygon_mask([(10, 10), (110, 10), (110, 110), (70, 110), (70, 60), (50, 60), (50, 110), (10, 110)])) == 0.0


def test_the_regression_learns_the_evidence_that_separates_and_calls_by_it():
    rng = np.random.default_rng(0)
    rows = [{"scene": "paper", "shape": shape, "gain": (0.05 if shape == "twobox" else -0.01) + 0.01 * rng.standard_normal(),
             "noise": rng.standard_normal(), "implausible": 0.0}
            for shape in ("box", "twobox") for _ in range(100)]
    model = regression(rows, ("gain", "noise", "implausible"))
    names, _, _, weights = model
    assert weights[names.index("gain")] > 1 and abs(weights[names.index("noise")]) < 0.3
    assert called(rows, model, 0.0) == [r["shape"] for r in rows]
    gated = [r | {"implausible": 1.0} for r in rows]  # a gate sets the twobox aside whatever the regression says
    assert set(called(gated, model, 0.0)) == {"box"}
    assert shares(rows, called(gated, model, 0.0))["paper/box"] == 100.0


def test_the_witness_keeps_both_classes_fits_and_leaves_the_choice_as_it_was():
    chosen = fitter_module.choose_cuboid
    with Witness() as witness:
        assert fitter_module.choose_cuboid is not chosen
    assert fitter_module.choose_cuboid is chosen and witness.last == {}


def test_the_witness_keeps_both_classes_fits_and_the_evidence_is_finite():
    """Both classes' cuboids and the networks' own confidence (which `infer --cuboid` leaves NaN: the
    cuboids' IoU judges there), so that every piece of evidence is a number."""
    mask = polygon_mask([(30, 40), (70, 30), (110, 45), (105, 110), (70, 118), (28, 105)])
    with Witness() as witness:
        Fitter.from_shipped(FitOptions(device="cpu", cuboid=True)).fit(mask)
    assert set(witness.last["cuboids"]) == {"box", "twobox"}
    assert all(0 <= c <= 1 for c in witness.last["networks"].values())
    found = evidence(mask, witness.last)
    assert tuple(found) == EVIDENCE and all(np.isfinite(v) for v in found.values())
    # a convex hexagon, a box's silhouette: no notch but its staircase, its pixels about its hull's area (centres: a little less)
    assert found["roof_notch"] < 1 / 80 and 0.95 < found["solidity"] < 1.05


def test_the_breakdown_reads_what_was_drawn_and_splits_each_class_by_it():
    twobox = drawn({"height_ratio": 0.8, "occluded_fraction": 0.3, "deviations": [{"kind": "roof"}, {"kind": "blob"}]})
    assert twobox["height_ratio"] == 0.8 and twobox["roof"] and twobox["blob"] and not twobox["neighbour"]
    box = drawn({"occluded_fraction": 0.0})  # a box has no height ratio; a paper sample no deviations
    assert box["height_ratio"] is None and not any(box[k] for k in ("roof", "chimney", "parapet", "neighbour", "blob", "low_res"))
    rows = ([{"shape": "twobox", "right": right} | drawn({"height_ratio": ratio, "occluded_fraction": 0.0, "deviations": []})
             for ratio, right in ((0.4, True), (0.5, True), (0.7, True), (0.8, False), (0.84, True))]
            + [{"shape": "box", "right": right} | drawn({"occluded_fraction": hidden, "deviations": [{"kind": "neighbour"}] * n})
               for hidden, right, n in ((0.0, True, 0), (0.2, False, 1), (0.5, False, 1))])
    split = banded(rows)
    assert split["twobox"]["all"] == (80.0, 5)
    assert split["twobox"]["height_ratio < 0.6"] == (100.0, 2) and split["twobox"]["height_ratio 0.6-0.75"] == (100.0, 1)
    assert split["twobox"]["height_ratio >= 0.75"] == (50.0, 2)
    assert split["box"]["all"] == (33.3, 3) and "height_ratio < 0.6" not in split["box"]
    assert [split["box"][f"occluded_fraction {band}"] for band in ("< 0.1", "0.1-0.25", ">= 0.25")] == [(100.0, 1), (0.0, 1), (0.0, 1)]
    assert split["box"]["neighbour"] == (0.0, 2) and split["box"]["no neighbour"] == (100.0, 1)
    assert np.isnan(split["box"]["roof"][0]) and split["box"]["roof"][1] == 0  # no mask with it: no share, not 0%


def test_the_breakdown_scores_infers_call_on_each_drawn_irregular_mask(tmp_path, monkeypatch):
    import bench_accuracy as ba

    called_with = []

    class Caller:  # `infer`'s choice stood in for: box on every mask, so boxes are all right, twoboxes all wrong
        def fit(self, mask):
            called_with.append(mask.shape)
            return type("Fit", (), {"shape": "box"})()

    monkeypatch.setattr(ba, "SEEDS", {**ba.SEEDS, ("box", "irregular"): 5, ("twobox", "irregular"): 6})
    rows = irregular_calls(Caller(), tmp_path, samples=3, offset=0)
    assert called_with and all(shape == (256, 256) for shape in called_with)
    assert {r["shape"] for r in rows} == {"box", "twobox"} and len(rows) == len(called_with) <= 6
    assert all(r["right"] == (r["shape"] == "box") for r in rows)
    assert all(0.35 <= r["height_ratio"] <= 0.85 for r in rows if r["shape"] == "twobox")
    assert all(r["height_ratio"] is None for r in rows if r["shape"] == "box")
