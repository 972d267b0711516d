"""The trainer's dashboard renders a status as text, logs it as one line, and
`watch` shows a run's status.json from another terminal."""
from __future__ import annotations

import io
import json
import logging
import os
import re
import subprocess
import threading

import pytest
from rich.console import Console

from cuboidtrain.train.monitor.dashboard import CHANGE_STEPS, Dashboard, fmt_duration, log_line, render, sparkline, trend, wait_cell, watch
from cuboidtrain.train.monitor.status import TrainerStatus, read_status, write_status

NOW = 1_700_000_000.0


def status(**changes) -> TrainerStatus:
    values = {
        "phase": "1", "shape": "box", "size": 64, "device": "cuda:0", "out": "runs/p1", "spool": "data_spool",
        "state": "training", "pid": os.getpid(), "started": NOW - 600, "updated": NOW - 1,
        "step": 120, "steps_total": 1000, "epoch": 3, "epochs_total": None, "batch_in_epoch": 7, "batches_in_epoch": 312,
        "losses": {"D_R": 0.05, "D_S": 1.2, "D_T": 3.4, "total": 4.65},
        "loss_history": {"D_R": [0.1] * 20 + [0.05] * 20, "D_S": [1.2, 1.2], "D_T": [3.0] * 20 + [3.4] * 20,
                         "total": [5.0, 4.65]},
        "loss_weights": [1.0, 0.5, 2.0],
        "samples_per_s": 41.0, "step_time_s": 0.78, "data_wait_fraction": 0.012,
        "freshness": {"mean_age_s": 35.2, "mean_reuse": 1.4},
        "skipped": {"vanished": 3, "corrupt": 1, "other_shape": 0, "other_size": 0},
        "spool_samples": 10_000, "spool_arrivals_per_s": 850.0, "eta_s": 1234.0,
        "last_checkpoint": {"path": "runs/p1/last.pt", "step": 100, "time": NOW - 125},
        "val": {"step": 100, "mean_px_error": 2.3, "median_px_error": 1.9},
        "notes": ["spool is small: samples are reused"],
    }
    values.update(changes)
    return TrainerStatus.from_json(values)


def as_text(renderable) -> str:
    console = Console(record=True, width=120, color_system=None, file=io.StringIO())
    console.print(renderable)
    return console.export_text()


def record_console() -> Console:
    return Console(record=True, width=120, color_system=None, file=io.StringIO())


def test_render_shows_progress_losses_throughput_and_spool():
    text = as_text(render(status(), now=NOW))
    for expected in ("phase 1 (separate networks)", "box 64x64 px", "cuda:0", "training",
                     "step 120 / 1,000", "12.0%", "epoch 3", "batch 7 / 312", "ETA 20m34s",
                     "0.0500", "1.200", "3.400", "4.650", "Refiner", "Tabulator",
                     "41.0 samples/s", "0.78 s/step", "1.2%", "10,000 samples", "850 arriving/s",
                     "mean age 35s", "mean reuse 1.4", "4 (vanished 3, corrupt 1, other shape 0, other size 0)",
                     "step 100, 2m05s ago", "mean 2.30 px, median 1.90 px", "spool is small"):
        assert expected in text, expected
    assert "↓ 50%" in text and "↑ 13%" in text  # D_R fell 0.1 -> 0.05, D_T rose 3.0 -> 3.4 (20 steps each)
    assert "loader starving" not in text


def test_each_loss_row_carries_its_weight():
    rows = {line.split()[1]: line.split() for line in as_text(render(status(), now=NOW)).splitlines()
            if len(line.split()) > 1 and line.split()[1] in ("D_R", "D_S", "D_T")}
    assert rows["D_R"][3:5] == ["0.0500", "1"] and rows["D_S"][3:5] == ["1.200", "0.5"]
    assert rows["D_T"][3:5] == ["3.400", "2"]


def test_data_wait_over_five_percent_is_flagged():
    text = as_text(render(status(data_wait_fraction=0.12), now=NOW))
    assert "12.0% > 5%: loader starving" in text
    assert wait_cell(0.12).style == "bold red" and wait_cell(0.04).style == ""


def test_unknown_values_render_as_dashes():
    blank = TrainerStatus.from_json({key: None for key in status().to_json()})
    text = as_text(render(blank, now=NOW))
    assert "phase — · — · — · —" in text and "step —  epoch —" in text and "ETA —" in text
    assert re.search(r"data wait +—", text) and re.search(r"D_R +Refiner +— +— +— +—", text)
    assert "total" in as_text(render(TrainerStatus(), now=NOW))  # even an empty status draws the loss table
    assert "step — epoch —" in log_line(blank)


def test_phase_two_and_ablations_are_named():
    assert "phase 2 (chained)" in as_text(render(status(phase="2"), now=NOW))
    assert "ablation" in as_text(render(status(phase="finetune"), now=NOW))


def test_formatting_helpers():
    assert fmt_duration(42) == "42s" and fmt_duration(185) == "3m05s" and fmt_duration(3725) == "1h02m"
    assert fmt_duration(None) == "—" and fmt_duration(float("nan")) == "—"
    assert sparkline([1, 2, 3, 4, 5, 6, 7, 8]) == "▁▂▃▄▅▆▇█"
    assert sparkline(list(range(100))) .__len__() == 30  # only the last 30 points
    assert sparkline([2.0, 2.0]) == "▄▄" and sparkline([]) == "—" and sparkline(None) == "—"
    assert trend([4, 4, 1, 1], steps=2).plain == "↓ 75%" and trend([1.0]).plain == "—"


def test_the_change_compares_the_last_steps_with_those_before_and_says_so():
    window = CHANGE_STEPS
    after_init = [0.2] * 5 + [1.0] * (window - 5) + [0.6] * window  # low just after --init, then falling
    assert trend(after_init).plain.startswith("↓") and trend(after_init).style == "green"
    noisy = [0.001] + [1.0, 1.1] * window  # a first point near zero: no "up 4031%"
    assert trend(noisy).plain == "→ +0%"
    assert trend([1.0] * (2 * window - 1)).plain == "—"  # too few steps for two windows: no figure
    assert trend([2.0] * window + [1.0] * window).plain == "↓ 50%"
    text = as_text(render(status(), now=NOW))
    assert f"change (last {window} steps vs {window} before)" in text


def test_log_line_has_the_figures():
    line = log_line(status())
    assert line.startswith("step 120/1000 epoch 3 eta 20m34s | D_R 0.0500 D_S 1.200 D_T 3.400 total 4.650 | ")
    for expected in ("41.0 samples/s wait 1.2%", "age 35s reuse 1.4", "skipped 4", "ckpt step 100",
                     "val 2.30 px", "spool is small"):
        assert expected in line, expected
    assert log_line(status(state="waiting for samples")).startswith("waiting for samples | step 120")


def test_write_then_read_status_round_trips(tmp_path):
    out = tmp_path / "run"
    write_status(out, status())
    write_status(out, status(step=121))  # replaces, leaving no temp file behind
    assert read_status(out) == status(step=121)
    assert [p.name for p in out.iterdir()] == ["status.json"]


def test_read_status_names_a_garbled_file(tmp_path):
    (tmp_path / "status.json").write_text('{"step": 1')
    with pytest.raises(ValueError, match="status.json: not valid JSON"):
        read_status(tmp_path)


def test_watch_once_renders_the_step(tmp_path):
    write_status(tmp_path, status(step=777))
    console = record_console()
    assert watch(tmp_path, once=True, console=console) == 0
    text = console.export_text()
    assert "step 777 / 1,000" in text and "not running" not in text


def test_watch_without_status_json_says_so(tmp_path):
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path}: no status.json")):
        watch(tmp_path, once=True, console=record_console())


def dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()  # reaped: the pid no longer exists
    return proc.pid


def test_watch_notes_a_dead_trainer(tmp_path):
    pid = dead_pid()
    write_status(tmp_path, status(pid=pid))
    console = record_console()
    assert watch(tmp_path, console=console) == 1  # returns at once: nothing will change
    assert f"trainer (pid {pid}) is not running; showing its last status" in console.export_text()
    write_status(tmp_path, status(pid=pid, state="done"))  # a finished run is no cause for alarm
    console = record_console()
    assert watch(tmp_path, once=True, console=console) == 0 and "not running" not in console.export_text()


def test_watch_follows_the_file_until_done(tmp_path):
    write_status(tmp_path, status(step=5))
    finisher = threading.Timer(0.1, write_status, (tmp_path, status(step=1000, state="done")))
    finisher.start()
    console = record_console()
    try:
        assert watch(tmp_path, interval=0.02, console=console) == 0
    finally:
        finisher.join()
    text = console.export_text()
    assert "step 1,000 / 1,000" in text and "done" in text


def test_log_mode_logs_on_interval_and_on_state_change(caplog):
    caplog.set_level(logging.INFO, logger="cuboidtrain.train.monitor.dashboard")
    with Dashboard(live=False, log_interval=3600.0) as board:
        board.update(status(step=1))  # the first update always logs
        board.update(status(step=2))  # within the interval, same state: held back
        assert [r.getMessage().split(" epoch")[0] for r in caplog.records] == ["step 1/1000"]
        board.update(status(step=3, state="checkpointing"))  # a new state logs at once
        board.update(status(step=4, state="checkpointing"))
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3 and messages[1].startswith("checkpointing | step 3/")
    assert messages[2].startswith("checkpointing | step 4/")  # close() logs the last figures


def test_live_mode_leaves_the_last_panel_on_screen():
    console = record_console()
    with Dashboard(live=True, console=console) as board:
        board.update(status(step=10))
        board.update(status(step=11))
    assert "step 11 / 1,000" in console.export_text()


# ---- a live status while a step runs, and a stop asked for during one ---------------------


def test_the_live_panel_leaves_room_for_the_echoed_ctrl_c():
    from shared.console import ECHO_ROOM

    out = io.StringIO()
    board = Dashboard(live=True, console=Console(file=out, force_terminal=True, width=100, color_system=None))
    board.update(status())
    board.close()
    lines = [re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", line) for line in out.getvalue().splitlines()]
    assert max(len(line) for line in lines) == 100 - ECHO_ROOM


def test_a_stop_is_seen_before_its_handler_runs(tmp_path):
    import signal

    from cuboidtrain.train.stop_and_wait import StopRequest

    with StopRequest().installed() as stop:
        write = signal.set_wakeup_fd(-1)  # the pipe the signal module writes each signal's number to
        signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        os.write(write, bytes([signal.SIGCHLD]))  # another signal: not a stop
        assert not stop.asked()
        os.write(write, bytes([signal.SIGINT]))  # as the C-level handler writes it, before Python's runs
        assert stop.asked() and not stop
    assert signal.set_wakeup_fd(-1) == -1  # the previous wakeup file is back


def test_status_stays_fresh_through_a_long_step_and_says_when_a_stop_waits_for_it(tmp_path, monkeypatch):
    import signal
    import time

    import cuboidtrain.train.loop as train_module
    from cuboidtrain.train.monitor import publisher
    from shared.sample import encode
    from shared.spool import SpoolWriter
    from tests.conftest import build_sample, train_config

    # The publisher's clock at a fifth (a publish every 0.2 s, not 1 s; a beat every 0.05 s), the
    # step's reads with it: the same sequence of statuses in 1.6 s instead of 4.5.
    monkeypatch.setattr(publisher, "PUBLISH_EVERY", 0.2)
    monkeypatch.setattr(publisher, "HEARTBEAT_EVERY", 0.05)
    spool, out = tmp_path / "spool", tmp_path / "run"
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(4):
            writer.publish(encode(build_sample(seed, size=32)))
    real_step, seen = train_module.train_step, []

    def slow_step(*args, **kwargs):  # a 17 s CPU step, shortened: status.json must not wait for its end
        if not seen:
            for when in (0.3, 1.0, 1.6):
                time.sleep(when - (seen[-1][0] if seen else 0))
                seen.append((when, time.time(), json.loads((out / "status.json").read_text())))
                if when == 1.0:  # read before the signal: the heartbeat may see it at once
                    os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the step
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_module, "train_step", slow_step)
    config = train_config(spool=str(spool), out=str(out), size=32, batch_size=2, loader_workers=0, dashboard=False)
    final = train_module.run(config)  # installs the Ctrl-C handler itself
    (_, t0, first), (_, t1, second), (_, t2, third) = seen
    assert first["state"] == "training" and second["state"] == "training"
    assert second["updated"] > first["updated"] and t1 - second["updated"] < 2 * publisher.PUBLISH_EVERY  # rewritten during the step
    assert third["state"] == "stopping after this step" and third["step"] == 0
    assert final.state == "stopped" and final.step == 1  # the step in hand was finished
    assert "stopping after this step" in as_text(render(TrainerStatus.from_json(third), now=third["updated"]))


class _NoWatcher:
    count = 0

    def arrivals_per_s(self):
        return 0.0


def test_status_follows_steps_slower_than_the_publish_interval(tmp_path, monkeypatch):
    # The heartbeat refreshes status.json between steps; it must not reset the loop's own
    # throttle, or a step that ends just after a beat is never published (status stuck at step 0).
    import time

    import torch

    from cuboidtrain.train.monitor import progress as progress_module
    from cuboidtrain.train.monitor import publisher
    from cuboidtrain.train.config import TrainConfig
    from cuboidtrain.data.sampler import EpochPosition

    monkeypatch.setattr(publisher, "PUBLISH_EVERY", 0.05)
    monkeypatch.setattr(publisher, "HEARTBEAT_EVERY", 0.01)
    config = TrainConfig(out=str(tmp_path), steps=4, arch="tiny")
    sampler = type("Sampler", (), {"where": lambda s: EpochPosition(epoch=0, taken=0, batches=4)})()
    losses = {"D_R": 1.0, "D_S": 1.0, "D_T": 1.0, "total": 3.0}
    with progress_module.Progress(config, torch.device("cpu"), _NoWatcher()) as progress:
        progress.begin(0, sampler)
        for step in range(1, 5):
            time.sleep(0.12)  # a step longer than the publish interval, beats in between
            progress.step(step, losses, 2, 0.0, 0.0, 0.0, {})
            assert read_status(tmp_path).step == step
