"""benchmarks/gpu/choose_campaign_model.py end to end with tiny settings: every candidate trains on the
same samples, is scored along its curve on the same masks, and is timed against the shipped models."""
import json
import sys
from pathlib import Path

import pytest

from shared.errors import UsageError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "gpu"))
import choose_campaign_model as choose  # noqa: E402

SAMPLES, BATCH, SHARES = 8, 4, 2
MASKS = 1  # a set's masks: every figure is asserted present and where it comes from, none for its spread
CANDIDATES = ["tiny:32", "tiny:64"]


def options(folder: Path) -> list[str]:
    return ["--samples", str(SAMPLES), "--batch", str(BATCH), "--shares", str(SHARES), "--sets", "paper",
            "--masks", str(MASKS), "--latency-masks", "1", "--latency-rounds", "1", "--spools", str(folder / "spools"),
            "--runs", str(folder / "runs")]


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    folder = tmp_path_factory.mktemp("choose")
    stale = folder / "runs" / "tiny-32" / "box" / "run"  # a run cut short before: its ledger must not count
    stale.mkdir(parents=True)
    (stale / "ledger.jsonl").write_text(json.dumps({"step": 1, "rank": 0, "samples": [["stale", 0]]}) + "\n")
    out = choose.main(["--candidates", *CANDIDATES, "--rate-only", "tiny:96", "--rate-steps", "2",
                       "--rate-batch", "2", *options(folder), "--json", str(folder / "choose.json")])
    return out, json.loads((folder / "choose.json").read_text()), folder


def trained_rows(out: dict) -> list[dict]:
    return [row for row in out["rows"] if not row.get("rate_only")]


def test_every_candidate_trains_on_the_same_samples_in_the_same_order(result):
    out, *_ = result
    rows = trained_rows(out)
    assert [row["candidate"] for row in rows] == CANDIDATES
    for shape in ("box", "twobox"):
        runs = [row["shapes"][shape] for row in rows]
        assert {run["samples"] for run in runs} == {SAMPLES}
        assert len({run["samples_digest"] for run in runs}) == 1
    assert rows[0]["shapes"]["box"]["samples_digest"] != rows[0]["shapes"]["twobox"]["samples_digest"]


def test_each_curve_is_scored_from_random_weights_at_equal_shares_with_its_gain(result):
    out, *_ = result
    for row in trained_rows(out):
        for run in row["shapes"].values():
            curve = run["curve"]
            assert [p["samples"] for p in curve] == [0, SAMPLES // 2, SAMPLES]
            for point in curve:
                figures = point["sets"]["paper"]
                assert figures["masks"] == MASKS
                assert set(figures) >= {"mean_256", "median_256", "outline_mean_256", "interior_mean_256", "ratio_error"}
                assert point["error"] == pytest.approx(figures["mean_256"])  # one set: its mean
            assert run["gain_per_1k"] == pytest.approx(1000 * (curve[0]["error"] - curve[-1]["error"]) / SAMPLES)
            assert run["cpu_samples_per_s"] > 0
            assert 0 <= run["budget"]["refiner_iou"] <= 1 and run["budget"]["t_alone_256"] >= 0
        assert set(row["shape_accuracy"]) == {SAMPLES // 2, SAMPLES}
        assert all(0 <= a <= 1 for a in row["shape_accuracy"].values())
        assert row["gpu"] is None  # no H100 figure for the tiny arch


def test_latency_is_against_the_shipped_models_in_the_same_process(result):
    out, written, _ = result
    for path in ("networks", "record"):
        timed = out["latency"][path]
        assert set(timed) == {"shipped", *CANDIDATES, "tiny:96"}
        assert timed["shipped"]["ratio"] == 1.0
        assert all(t["ms"] > 0 and t["ratio"] == pytest.approx(t["ms"] / timed["shipped"]["ms"]) for t in timed.values())
        assert timed[CANDIDATES[0]]["over_first"] == 1.0
        assert all(t["over_first"] == pytest.approx(t["ms"] / timed[CANDIDATES[0]]["ms"]) for t in timed.values())
    slow = [row for row in out["rows"] if row.get("rate_only")]
    assert [row["candidate"] for row in slow] == ["tiny:96"] and slow[0]["cpu_samples_per_s"] > 0
    assert written["rows"][0]["candidate"] == CANDIDATES[0]  # the JSON holds what was returned


def test_the_projection_is_the_measured_h100_rate_over_an_eight_minute_lease():
    projected = choose.projection(choose.Candidate.parse("slim:128"))
    low, high = choose.GPU_RATES["slim", 128]
    assert projected["samples_per_lease"] == [low * 480, high * 480]
    assert choose.projection(choose.Candidate.parse("compact:256")) is None


@pytest.mark.parametrize("samples,batch,shares", [(8, 4, 2), (4000, 32, 4), (100, 32, 8), (5, 8, 3)])
def test_curve_points_rise_to_the_runs_last_step(samples, batch, shares):
    points = choose.curve_points(samples, batch, shares)
    assert points == sorted(set(points)) and points[0] >= 1
    assert points[-1] == max(1, samples // batch)


@pytest.mark.parametrize("text", ["slim", "slim:abc", "nope:128", "slim:100", "slim:128:0", "slim:128:3:1"])
def test_a_bad_candidate_is_a_one_line_error_naming_it(text):
    with pytest.raises(UsageError, match=f"candidate {text!r}"):
        choose.Candidate.parse(text)


def test_a_candidate_takes_its_sizes_sigma_unless_given():
    assert choose.Candidate.parse("compact:64").sigma == 2.0
    assert choose.Candidate.parse("slim:128").sigma == 3.0
    assert choose.Candidate.parse("slim:128:2.5") == choose.Candidate("slim", 128, 2.5)


def test_a_later_call_reports_the_runs_kept_without_training_again(result):
    out, _, folder = result
    again = choose.main(["--candidates", CANDIDATES[1], "--rate-only", "--cached-only", *options(folder)])
    assert again["rows"][0]["shapes"] == json.loads(json.dumps(trained_rows(out)[1]["shapes"]))  # budget: the same model's
    other = choose.main(["--candidates", CANDIDATES[1], "--rate-only", "--cached-only", *options(folder)[2:],
                         "--samples", str(2 * SAMPLES)])
    assert other["rows"][0]["shapes"] == {}  # trained for another number of samples: not reused
