"""The training loop's reporter, part by part: running statistics, the metrics log and the status publisher."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cuboidtrain.train.monitor import metrics_log, publisher, stats
from cuboidtrain.train.monitor.metrics_log import MetricsLog
from cuboidtrain.train.monitor.publisher import STOPPING, StatusPublisher
from cuboidtrain.train.monitor.stats import Rates, RunningStats
from cuboidtrain.train.monitor.status import BatchFreshness, TrainerStatus, Validation, read_status

LOSSES = {"D_R": 1.0, "D_S": 2.0, "D_T": 3.0, "total": 6.0}
ROOT = Path(__file__).resolve().parents[1]


class Clock:
    def __init__(self, now: float = 100.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


# ---- RunningStats


def test_rates_measure_samples_step_time_and_data_wait(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(stats.time, "perf_counter", clock)
    figures = RunningStats()
    assert figures.rates() == Rates(None, None, None)
    for _ in range(2):
        clock.now += 0.5
        assert figures.fetched() == pytest.approx(0.5)
        clock.now += 1.5
        figures.stepped(LOSSES, 8, 0.5, 3.0, 1.0, {"vanished": 1})
    assert figures.rates() == Rates(samples_per_s=4.0, step_time_s=2.0, data_wait_fraction=0.25)
    assert figures.freshness == BatchFreshness(3.0, 1.0) and figures.skipped["vanished"] == 2
    assert not figures.window_full()


def test_rates_span_the_last_half_minute_when_steps_are_short(monkeypatch):
    # A GPU's steps: 0.1 s each, and every 50th waits 0.5 s more for an epoch's first batch.
    clock = Clock()
    monkeypatch.setattr(stats.time, "perf_counter", clock)
    figures, fractions = RunningStats(), []
    for step in range(1, 2001):
        waited = 0.5 if step % 50 == 0 else 0.0
        clock.now += 0.1 + waited
        figures.stepped(LOSSES, 256, waited, 0.0, 0.0, {})
        if step > 1000:
            fractions.append(figures.rates().data_wait_fraction)
    mean = 0.5 / (50 * 0.1 + 0.5)  # 9.1%: one epoch's start in 50 steps
    assert figures.window_full() and stats.WINDOW_S <= sum(r[2] for r in figures.recent) < stats.WINDOW_S + 1
    assert all(abs(f - mean) < 0.02 for f in fractions)  # steady, where 20 steps swung between 0% and 20%
    assert figures.rates().samples_per_s == pytest.approx(256 * 50 / 5.5, rel=0.05)
    for _ in range(stats.WINDOW + 5):  # slow steps: the window keeps WINDOW of them, whatever their span
        clock.now += 10.0
        figures.stepped(LOSSES, 8, 1.0, 0.0, 0.0, {})
    assert len(figures.recent) == stats.WINDOW and figures.rates().data_wait_fraction == pytest.approx(0.1)


def test_losses_are_smoothed_kept_for_the_trend_and_averaged_per_record():
    figures = RunningStats()
    figures.stepped(LOSSES, 2, 0.0, 0.0, 0.0, {})
    figures.stepped({k: v + 1.0 for k, v in LOSSES.items()}, 2, 0.0, 0.0, 0.0, {})
    assert figures.smoothed["D_R"] == pytest.approx(1.0 + stats.EMA)
    assert list(figures.history["total"]) == [6.0, 7.0]
    assert figures.mean_losses() == {"D_R": 1.5, "D_S": 2.5, "D_T": 3.5, "total": 6.5}
    assert figures.mean_losses() == {}  # summing afresh after each record


# ---- MetricsLog


class FakeTensorBoard:
    def __init__(self):
        self.scalars, self.closed = [], False

    def add_scalar(self, tag, value, step):
        self.scalars.append((tag, value, step))

    def close(self):
        self.closed = True


def test_a_record_is_one_metrics_line_and_the_same_figures_in_tensorboard(tmp_path, monkeypatch):
    board = FakeTensorBoard()
    monkeypatch.setattr(metrics_log, "tensorboard_writer", lambda out: board)
    log = MetricsLog(tmp_path)
    log.record(10, 1, LOSSES, Rates(4.0, 2.0, None), BatchFreshness(3.0, 1.0), {"vanished": 2})
    log.validated(Validation(10, 2.5, 2.0))
    log.close()
    first, second = (json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines())
    assert list(first) == ["step", "epoch", "time", "D_R", "D_S", "D_T", "total", "samples_per_s", "step_time_s",
                           "data_wait_fraction", "mean_age_s", "mean_reuse", "skipped"]
    assert first["total"] == 6.0 and first["data_wait_fraction"] is None and first["skipped"] == {"vanished": 2}
    assert second["val"] == {"step": 10, "mean_px_error": 2.5, "median_px_error": 2.0}
    assert board.scalars == [("D_R", 1.0, 10), ("D_S", 2.0, 10), ("D_T", 3.0, 10), ("total", 6.0, 10),
                             ("speed/samples_per_s", 4.0, 10), ("val/mean_px_error", 2.5, 10)]
    assert board.closed


def test_a_rank_that_does_not_write_logs_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(metrics_log, "tensorboard_writer", lambda out: pytest.fail("rank 0 alone writes"))
    log = MetricsLog(tmp_path, writes=False)
    log.record(1, 0, LOSSES, Rates(), BatchFreshness(), {})
    log.validated(Validation(1, 1.0, 1.0))
    assert not (tmp_path / "metrics.jsonl").exists()


# ---- StatusPublisher


class Asked:
    def asked(self) -> bool:
        return True


def test_the_loop_publishes_at_most_once_a_second_unless_forced(tmp_path, monkeypatch):
    clock = Clock()
    monkeypatch.setattr(publisher.time, "monotonic", clock)
    status = StatusPublisher(tmp_path)
    assert status.due() and not status.due() and status.due(force=True)
    clock.now += publisher.PUBLISH_EVERY
    assert status.due()
    assert not StatusPublisher(tmp_path, writes=False).due(force=True)


def test_a_stop_request_shows_stopping_until_the_step_in_hand_ends(tmp_path):
    status = StatusPublisher(tmp_path, stop=Asked())
    assert status.enter("training") and not status.enter("training")
    status.show(TrainerStatus(state="training", step=3))
    status.beat()  # the heartbeat sees the stop before the loop does
    assert status.state == STOPPING and read_status(tmp_path).state == STOPPING
    assert read_status(tmp_path).step == 3
    assert not status.enter("training") and not status.enter("waiting for samples")
    assert status.enter("checkpointing") and status.state == "checkpointing"


# ---- walls


def test_only_the_sampler_reads_or_moves_its_state():
    # The loop and the reporter ask the sampler (advance, end_epoch, where, snapshot).
    offenders = [p.relative_to(ROOT) for p in (ROOT / "cuboidtrain").rglob("*.py")
                 if p.name != "data.py" and any(s in p.read_text() for s in ("sampler.state", "sampler._state"))]
    assert not offenders
