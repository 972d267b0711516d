"""The trainer's status: what a run reports about itself in OUT/status.json.

The trainer (cuboidtrain.train.monitor.publisher) writes it about once a second; the dashboard renders
it; `watch` and the compose healthcheck read it back from another process. Every field
may be None (or empty) while it is not known yet, and a file written by an older
version may lack fields or hold ones no longer written: reading keeps what it knows.
Whether the trainer died mid-run is told by `trainer_died`, with the same liveness rule
as the spool's orphan sweep (shared.files.process_alive: a zombie is dead).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from shared.errors import UsageError
from shared.files import process_alive, write_json

STATUS_FILE = "status.json"
FINISHED = ("done", "stopped", "gave up", "failed")  # states after which no update comes


class TrainingFailed(RuntimeError):
    """A run that cannot go on through no bad option (a full disk, a spool that never fills):
    its status ends `failed` (or `gave up`) with this one-line message, the command line prints
    it and exits 1, and what was written before is kept."""


@dataclass(slots=True)
class Checkpoint:
    """The last checkpoint written."""

    path: str | None = None
    step: int | None = None
    time: float | None = None  # unix s


@dataclass(slots=True)
class Validation:
    """The last validation's result."""

    step: int | None = None
    mean_px_error: float | None = None
    median_px_error: float | None = None


@dataclass(slots=True)
class BatchFreshness:
    """How old the trained samples were and how often each was used, over the last step."""

    mean_age_s: float | None = None
    mean_reuse: float | None = None


# Fields holding one of the classes above: JSON objects, made typed again when read.
_NESTED = {"last_checkpoint": Checkpoint, "val": Validation, "freshness": BatchFreshness}


@dataclass(slots=True)
class TrainerStatus:
    """One training run's status; its JSON form (`to_json`) is status.json, key for key."""

    phase: str | None = None
    phase_meaning: str | None = None
    shape: str | None = None
    size: int | None = None
    device: str | None = None
    out: str | None = None
    spool: str | None = None
    state: str | None = None  # "starting", "training", ..., or one of FINISHED
    pid: int | None = None  # the trainer's process (rank 0's under torchrun)
    rank: int | None = None
    world_size: int | None = None
    started: float | None = None  # unix s
    updated: float | None = None  # unix s
    step: int | None = None
    steps_total: int | None = None
    epoch: int | None = None
    epochs_total: int | None = None
    batch_in_epoch: int | None = None
    batches_in_epoch: int | None = None
    loss_weights: list[float] = field(default_factory=list)
    last_checkpoint: Checkpoint | None = None
    val: Validation | None = None
    notes: list[str] = field(default_factory=list)
    idle: str | None = None  # why no sample can be trained on, while that lasts
    samples_per_s: float | None = None
    step_time_s: float | None = None
    data_wait_fraction: float | None = None  # of step time
    losses: dict[str, float] = field(default_factory=dict)  # smoothed, by loss name (D_R, ..., total)
    loss_history: dict[str, list[float]] = field(default_factory=dict)
    freshness: BatchFreshness | None = None
    skipped: dict[str, int] = field(default_factory=dict)  # samples skipped, by reason
    spool_samples: int | None = None
    spool_evicted_unread: int | None = None  # samples the generator evicted before this trainer read them
    foreign_files: int | None = None
    eta_s: float | None = None
    spool_arrivals_per_s: float | None = None
    replicas: list[dict] | None = None  # each torchrun rank's final step and weights hash, at the end

    def to_json(self) -> dict:
        """The JSON object of status.json."""
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "TrainerStatus":
        """The status in a JSON object; keys it does not know are ignored, missing or null ones left unknown."""
        known = _known(cls, data)
        for name, kind in _NESTED.items():
            value = known.get(name)
            known[name] = kind(**_known(kind, value)) if isinstance(value, dict) else None
        return cls(**known)

    def update(self, **changes) -> None:
        """Set fields in place (the trainer's running figures). Slots make a misspelt name an error."""
        for name, value in changes.items():
            setattr(self, name, value)

    def refreshed(self, **changes) -> "TrainerStatus":
        """A copy with `changes`, dated now (the heartbeat's: the same figures, still alive)."""
        return replace(self, **changes, updated=time.time())


def _known(cls, data: dict) -> dict:
    names = {f.name for f in fields(cls)}
    return {key: value for key, value in data.items() if key in names and value is not None}


def write_status(out: Path, status: TrainerStatus) -> None:
    """Replace OUT/status.json atomically, so a reader sees the old file or the new, never half."""
    write_json(Path(out) / STATUS_FILE, status.to_json())


def read_status(out: Path) -> TrainerStatus:
    """OUT/status.json; a one-line ValueError when it is missing or not a status."""
    path = Path(out) / STATUS_FILE
    try:
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError:  # replaces are atomic, but copies and network filesystems may tear
            time.sleep(0.05)
            data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UsageError(f"{out}: no status.json — is it a cuboidtrain run folder?") from None
    except json.JSONDecodeError as err:
        raise UsageError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise UsageError(f"{path}: expected a JSON object, found {type(data).__name__}")
    return TrainerStatus.from_json(data)


def trainer_died(status: TrainerStatus) -> bool:
    """Whether the run ended without finishing: not in a finished state, and its trainer is no
    live process on this host. An unknown pid is given the benefit of the doubt."""
    pid = status.pid
    known = isinstance(pid, int) and pid > 0
    return status.state not in FINISHED and known and not process_alive(pid)
