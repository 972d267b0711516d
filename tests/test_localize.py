"""Localization (paper section 5): eq. (2), the oracle, the ranking, the street JSON, the command.

Models are 64 px with random weights: they only carry the plumbing; what must be
right (matching, ranking) is tested on given ratios.
"""
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidgen.config import PAPER
from cuboidtrain.models.checkpoint import save_checkpoint
from cuboidtrain.cli import app
from cuboidtrain.experiments.localize_experiment import ExperimentConfig, draw_street, run_experiment, silhouette_of
from cuboidtrain.localize import (Building, accuracy, localize_masks, mask_sequence, rank_starts, read_street,
                                  start_probabilities, street_from_dict, street_to_dict,
                                  subsequence_distances, true_ranks)
from tests.conftest import small_library, tiny_model, train_config

SIZE = 64  # the smallest size a street's masks are drawn and fitted at in the CPU recipe
runner = CliRunner()


# --- builders ------------------------------------------------------------------

def street_of(ratios) -> list[Building]:
    """Buildings of height 1 with the given (depth/height, width/height) ratios."""
    return [Building(f"b{k + 1}", width=w, height=1.0, depth=d) for k, (d, w) in enumerate(ratios)]


def street_file(path: Path, buildings: list[dict], **changes) -> Path:
    path.write_text(json.dumps({"format": "cuboid-fit/street", "version": 1, "buildings": buildings} | changes))
    return path


def brute_force_accuracy(true, predicted, max_m, top_l):
    """Eq. (2) written out loop by loop, ties against the true start."""
    n, acc = len(true), np.zeros((max_m, top_l))
    for m in range(1, max_m + 1):
        starts = range(n - m + 1)
        for i in starts:
            d = [np.linalg.norm(predicted[i : i + m] - true[j : j + m]) for j in starts]
            rank = sum(d[j] <= d[i] for j in starts)
            for l in range(1, top_l + 1):
                acc[m - 1, l - 1] += (rank <= l) / len(starts)
    return acc


# --- eq. (2) -------------------------------------------------------------------

def test_accuracy_matches_a_hand_worked_street():
    true = np.array([[1, 1], [2, 2], [3, 3], [4, 4]], float)
    predicted = np.array([[1, 1], [3, 3], [3, 3], [4, 4]], float)
    # m = 1: building 2 (predicted (3, 3)) is nearer to true building 3 (distance 0) and tied
    #   with building 4 (sqrt 2): rank 3. The others are exact: rank 1.
    # m = 2: start 0 ties with start 1 (d^2 = 2 each) and start 1 ties with start 2: rank 2 each;
    #   start 2 is exact. m = 3: both predicted sub-sequences are nearest to their own start.
    expected = [[3 / 4, 3 / 4, 1], [1 / 3, 1, 1], [1, 1, 1]]
    np.testing.assert_allclose(accuracy(true, predicted, max_m=3, top_l=3), expected)


def test_a_tie_counts_against_the_true_start():
    distances = np.array([[1.0, 1.0, 2.0], [0.5, 1.0, 3.0], [0.0, 0.0, 0.0]])
    assert true_ranks(distances).tolist() == [2, 2, 3]


@pytest.mark.parametrize("seed", range(3))
def test_accuracy_equals_the_loop_by_loop_definition(seed):
    rng = np.random.default_rng(seed)
    true = rng.uniform(0.25, 4, (12, 2))
    predicted = true * (1 + 0.3 * rng.standard_normal(true.shape))
    np.testing.assert_allclose(accuracy(true, predicted, 6, 4), brute_force_accuracy(true, predicted, 6, 4))


def test_subsequence_distances_cover_every_start():
    true = np.arange(10.0).reshape(5, 2)
    shapes = [(m, d.shape) for m, d in subsequence_distances(true, true + 1, 5)]
    assert shapes == [(m, (6 - m, 6 - m)) for m in range(1, 6)]


@pytest.mark.parametrize("seed", range(10))
def test_accuracy_never_decreases_as_l_grows(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    true = rng.uniform(0.25, 4, (n, 2))
    if seed % 3 == 0:
        true[rng.integers(n, size=n // 2)] = true[0]  # repeated buildings: many ties
    predicted = true * (1 + rng.uniform(0, 0.5) * rng.standard_normal(true.shape))
    acc = accuracy(true, predicted, max_m=n, top_l=n + 2)
    assert (np.diff(acc, axis=1) >= 0).all()
    assert ((acc >= 0) & (acc <= 1)).all()
    # l covering every candidate always counts
    assert (acc[:, -1] == 1).all()


@pytest.mark.parametrize("changes, message", [
    ({"max_m": 11}, "--max-m 11"), ({"top_l": 0}, "--top-l 0"), ({"oracle_noise": -0.1}, "--oracle-noise -0.1"),
    ({"example_start": 8}, "--example-start 8"), ({"scene": "moon"}, "scene 'moon'"), ({"streets": 0}, "--streets 0"),
])
def test_bad_experiment_settings_name_the_value(changes, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        ExperimentConfig(**({"buildings": 10, "max_m": 5} | changes)).validate()


# --- the oracle and the street ----------------------------------------------------

def test_the_exact_oracle_locates_every_sub_sequence():
    result = run_experiment(ExperimentConfig(buildings=25, max_m=25, top_l=3, streets=2, oracle=True))
    assert np.array(result["acc"]).shape == (25, 3)
    assert (np.array(result["acc"]) == 1).all()
    assert result["m"] == list(range(1, 26)) and result["l"] == [1, 2, 3]


def test_a_noisy_oracle_is_wrong_sometimes_and_better_with_longer_sequences():
    acc = np.array(run_experiment(ExperimentConfig(buildings=60, max_m=8, top_l=1, oracle=True,
                                                   oracle_noise=0.3))["acc"])[:, 0]
    assert acc[0] < 0.5 and acc[-1] > acc[0]


def test_a_building_keeps_its_ratios_in_every_view():
    building = draw_street(1, PAPER, np.random.default_rng(3))[0]
    views = [silhouette_of(building, PAPER, SIZE, seed, small_library()) for seed in (1, 2)]
    for view in views:
        np.testing.assert_allclose([view.ratios["depth_height"], view.ratios["width_height"]], building.ratios)
        assert view.params["width"] == building.width and view.noisy.any()
    assert not np.array_equal(views[0].clean, views[1].clean)  # a new pose, not the same picture


# --- ranking (Figure 12) and the practical command ---------------------------------------

def test_the_ranking_puts_the_true_start_first():
    true = np.random.default_rng(5).uniform(0.25, 4, (10, 2))
    predicted = true[3:7] * (1 + 0.02 * np.random.default_rng(6).standard_normal((4, 2)))
    ranking = rank_starts(street_of(true), predicted)
    assert ranking[0]["start"] == 3 and ranking[0]["buildings"] == ["b4", "b5", "b6", "b7"]
    assert len(ranking) == 7 and sorted(r["start"] for r in ranking) == list(range(7))
    probabilities = [r["probability"] for r in ranking]
    assert probabilities == sorted(probabilities, reverse=True)
    assert sum(probabilities) == pytest.approx(1.0)


def test_start_probabilities_are_the_softmax_of_negative_distances():
    true = np.array([[1.0, 1.0], [2.0, 1.0], [4.0, 1.0]])
    distances, probabilities = start_probabilities(true, np.array([[2.0, 1.0]]))
    np.testing.assert_allclose(distances, [1, 0, 2])
    np.testing.assert_allclose(probabilities, np.exp([-1, 0, -2]) / np.exp([-1, 0, -2]).sum())


GOOD = {"name": "a", "width": 10, "height": 8, "depth": 12.5}


@pytest.mark.parametrize("data, message", [
    ({"buildings": [{"width": 1, "height": 2}]}, "buildings[0]: missing key 'depth'"),
    ({"buildings": [GOOD, GOOD | {"height": -3}]}, "buildings[1].height = -3, expected a positive number"),
    ({"buildings": [GOOD | {"width": "wide"}]}, "buildings[0].width = 'wide', expected a positive number"),
    ({"buildings": [GOOD], "format": "cuboid-fit/sample"}, "format 'cuboid-fit/sample', expected 'cuboid-fit/street'"),
    ({"buildings": [GOOD], "version": 2}, "version 2, expected 1"),
    ({"buildings": []}, "buildings = [], expected a non-empty list"),
])
def test_street_errors_name_the_value_and_what_was_expected(tmp_path, data, message):
    path = street_file(tmp_path / "s.json", **data)
    with pytest.raises(ValueError) as error:
        read_street(path)
    assert message in str(error.value) and str(path) in str(error.value) and "\n" not in str(error.value)


def test_street_json_round_trips(tmp_path):
    street = draw_street(4, PAPER, np.random.default_rng(0))
    (tmp_path / "s.json").write_text(json.dumps(street_to_dict(street)))
    assert read_street(tmp_path / "s.json") == street
    assert street_from_dict({"format": "cuboid-fit/street", "version": 1,
                             "buildings": [{"width": 1, "height": 2, "depth": 3}]})[0].name == "#1"


def test_more_masks_than_buildings_is_refused():
    street = street_of([[1, 1], [2, 2]])
    with pytest.raises(ValueError, match="3 masks for a street of 2 buildings: expected at most"):
        localize_masks(street, ["a.png", "b.png", "c.png"], models=[])


def test_a_street_needs_a_box_model():
    with pytest.raises(ValueError, match="needs a box model .* got twobox"):
        localize_masks(street_of([[1, 1]]), ["a.png"], models=[tiny_model("twobox", SIZE)])


def test_mask_sequence_keeps_street_order():
    assert mask_sequence(["a"], ["b", "c"]) == ["a", "b", "c"]  # --masks a b c
    assert mask_sequence(["a", "b"], []) == ["a", "b"]  # --masks a --masks b
    assert mask_sequence([], ["a", "b"]) == ["a", "b"]
    with pytest.raises(ValueError, match="not both"):
        mask_sequence(["a", "c"], ["b"])


# --- the command, end to end ---------------------------------------------------------

@pytest.fixture(scope="module")
def box_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "box.pt"
    return save_checkpoint(path, tiny_model("box", SIZE, seed=1).eval(), train_config(shape="box", size=SIZE), step=0)


@pytest.fixture(scope="module")
def street_and_masks(tmp_path_factory):
    """A street of 8 and masks of its buildings 3..6, drawn by the generator."""
    folder = tmp_path_factory.mktemp("street")
    street = draw_street(8, PAPER, np.random.default_rng(1))
    (folder / "street.json").write_text(json.dumps(street_to_dict(street)))
    masks = []
    for k in range(2, 6):
        sample = silhouette_of(street[k], PAPER, SIZE, seed=k, library=small_library())
        masks.append(str(folder / f"m{k}.png"))
        cv2.imwrite(masks[-1], sample.noisy.astype(np.uint8) * 255)
    return folder / "street.json", masks


def test_the_command_ranks_every_start_of_the_street(tmp_path, box_checkpoint, street_and_masks):
    street, masks = street_and_masks
    out, bars = tmp_path / "out.json", tmp_path / "bars.png"
    result = runner.invoke(app, ["localize", "--street", str(street), "--checkpoint", str(box_checkpoint),
                                 "--masks", *masks, "--json", str(out), "--bars", str(bars), "--threads", "1"])
    assert result.exit_code == 0, result.output
    answer = json.loads(out.read_text())
    assert [m["input"] for m in answer["masks"]] == masks
    assert sorted(r["start"] for r in answer["ranking"]) == list(range(5))  # 8 - 4 + 1 starts
    assert sum(r["probability"] for r in answer["ranking"]) == pytest.approx(1.0)
    assert "rank" in result.output and bars.stat().st_size > 0


@pytest.mark.parametrize("args, message", [
    (["--masks", "{m0}", "{m1}", "{m2}"], "3 masks for a street of 2 buildings"),
    ([], "--street: expected masks"),  # (an --oracle is the experiment's: `localize` has none)
])
def test_the_command_fails_in_one_line(tmp_path, box_checkpoint, street_and_masks, args, message):
    _, masks = street_and_masks
    street = street_file(tmp_path / "s.json", [GOOD, GOOD])
    args = [a.format(**{f"m{k}": m for k, m in enumerate(masks)}) for a in args]
    result = runner.invoke(app, ["localize", "--street", str(street), "--checkpoint", str(box_checkpoint), *args])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output


def test_the_experiment_command_writes_acc_and_its_figures(tmp_path, box_checkpoint):
    out = {name: tmp_path / name for name in ("acc.json", "acc.csv", "heat.png", "bars.png")}
    result = runner.invoke(app, ["localize-experiment", "--checkpoint", str(box_checkpoint), "--buildings", "6",
                                 "--max-m", "3",
                                 "--top-l", "2", "--example-m", "2", "--seed", "4", "--threads", "1",
                                 "--json", str(out["acc.json"]), "--csv", str(out["acc.csv"]),
                                 "--heatmap", str(out["heat.png"]), "--bars", str(out["bars.png"])])
    assert result.exit_code == 0, result.output
    answer = json.loads(out["acc.json"].read_text())
    assert np.array(answer["acc"]).shape == (3, 2) and answer["m"] == [1, 2, 3] and answer["l"] == [1, 2]
    assert answer["settings"]["buildings"] == 6 and answer["settings"]["seed"] == 4
    assert out["acc.csv"].read_text().splitlines()[0] == "m,top_1,top_2"
    assert all(out[name].stat().st_size > 0 for name in ("heat.png", "bars.png"))


def test_locating_needs_a_street_and_the_experiment_takes_no_masks(tmp_path):
    no_street = runner.invoke(app, ["localize", "a.png", "b.png"])
    assert no_street.exit_code == 2 and "--street" in no_street.output
    with_masks = runner.invoke(app, ["localize-experiment", "a.png"])
    assert with_masks.exit_code == 2 and "unexpected extra argument" in with_masks.output.lower()


def test_the_experiment_command_rejects_a_long_m(tmp_path):
    result = runner.invoke(app, ["localize-experiment", "--oracle", "--buildings", "10", "--max-m", "30"])
    assert result.exit_code == 2 and "--max-m 30: expected 1 to --buildings (10)" in result.output
