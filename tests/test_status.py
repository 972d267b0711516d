"""The trainer's status: a typed record whose JSON form is status.json, read back whole,
tolerant of files from older versions, and one rule for a trainer that died mid-run."""
from __future__ import annotations

import json
import os

import pytest

from cuboidtrain.train.monitor.status import (
    FINISHED, BatchFreshness, Checkpoint, TrainerStatus, Validation, read_status, trainer_died, write_status,
)
from tests.test_files import dead_pid

# status.json as the trainer wrote it before the status was typed (every key it held then).
WRITTEN_BEFORE = {
    "phase": "1", "phase_meaning": "separate networks", "shape": "box", "size": 64, "device": "cpu",
    "out": "runs/p1", "spool": "data_spool", "state": "training", "pid": 4242, "rank": 0, "world_size": 1,
    "started": 1.7e9, "updated": 1.7e9 + 60, "step": 120, "steps_total": 1000, "epoch": 3, "epochs_total": None,
    "batch_in_epoch": 7, "batches_in_epoch": 312, "loss_weights": [1.0, 0.5, 2.0],
    "last_checkpoint": {"path": "runs/p1/last.pt", "step": 100, "time": 1.7e9 + 30},
    "val": {"step": 100, "mean_px_error": 2.3, "median_px_error": 1.9},
    "notes": ["a note"], "idle": None, "samples_per_s": 41.0, "step_time_s": 0.78, "data_wait_fraction": 0.012,
    "losses": {"D_R": 0.05, "total": 4.65}, "loss_history": {"D_R": [0.1, 0.05]},
    "freshness": {"mean_age_s": 35.2, "mean_reuse": 1.4},
    "skipped": {"vanished": 3, "corrupt": 1, "other_shape": 0, "other_size": 0},
    "spool_samples": 10_000, "spool_evicted_unread": 5, "foreign_files": 0, "eta_s": 1234.0,
    "spool_arrivals_per_s": 850.0, "replicas": [{"rank": 0, "step": 120, "weights": "ab12"}],
}


def test_status_json_keys_and_values_survive_a_round_trip():
    status = TrainerStatus.from_json(WRITTEN_BEFORE)
    assert status.to_json() == WRITTEN_BEFORE  # the same keys as ever, and nothing lost
    assert status.last_checkpoint == Checkpoint("runs/p1/last.pt", 100, 1.7e9 + 30)
    assert status.val == Validation(100, 2.3, 1.9) and status.freshness == BatchFreshness(35.2, 1.4)
    assert TrainerStatus.from_json(json.loads(json.dumps(status.to_json()))) == status


def test_write_then_read_gives_the_same_status_and_no_temporary_file(tmp_path):
    status = TrainerStatus.from_json(WRITTEN_BEFORE)
    write_status(tmp_path / "run", status)
    assert read_status(tmp_path / "run") == status
    assert os.listdir(tmp_path / "run") == ["status.json"]


def test_an_older_file_reads_with_what_it_has():
    old = {"state": "training", "pid": 4242, "step": 7, "retired_key": 1,
           "last_checkpoint": {"step": 5}, "freshness": None, "skipped": None, "notes": None}
    status = TrainerStatus.from_json(old)
    assert (status.state, status.pid, status.step) == ("training", 4242, 7)
    assert status.last_checkpoint == Checkpoint(step=5) and status.freshness is None
    assert status.skipped == {} and status.notes == [] and status.losses == {}  # null: unknown, as if missing
    assert "retired_key" not in status.to_json()
    assert TrainerStatus.from_json({}) == TrainerStatus()


def test_a_misspelt_field_is_an_error_not_a_new_key():
    with pytest.raises(AttributeError):
        TrainerStatus().update(stpe=3)


@pytest.mark.parametrize("content, message", [
    ('{"step": 1', "not valid JSON"), ("[1, 2]", "expected a JSON object, found list"),
])
def test_a_file_that_is_no_status_is_a_one_line_error(tmp_path, content, message):
    (tmp_path / "status.json").write_text(content)
    with pytest.raises(ValueError, match=message):
        read_status(tmp_path)


def test_a_trainer_died_when_unfinished_and_its_process_is_gone():
    gone = dead_pid()
    assert trainer_died(TrainerStatus(state="training", pid=gone))
    assert not trainer_died(TrainerStatus(state="training", pid=os.getpid()))
    for state in FINISHED:  # a finished run's process is meant to be gone
        assert not trainer_died(TrainerStatus(state=state, pid=gone))
    for unknown in (None, 0, -1):  # no pid to ask: not declared dead
        assert not trainer_died(TrainerStatus(state="training", pid=unknown))
