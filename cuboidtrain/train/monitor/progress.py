"""The training loop's reporter: turns the loop's events into running statistics, metrics records and status.

The loop tells `Progress` what happened (a batch fetched, a step taken, a
checkpoint written); Progress hands each event to the part whose role it is —
`RunningStats` (cuboidtrain.train.monitor.stats) keeps the figures, `MetricsLog`
(cuboidtrain.train.monitor.metrics_log) appends metrics.jsonl and TensorBoard records,
`StatusPublisher` (cuboidtrain.train.monitor.publisher) writes status.json and the
dashboard and runs the heartbeat — and composes the status they publish.
"""
from __future__ import annotations

import logging
import os
import time
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from cuboidtrain.train.config import PHASES, TrainConfig
from cuboidtrain.data.sampler import EpochPosition
from cuboidtrain.train.monitor.metrics_log import MetricsLog
from cuboidtrain.train.monitor.publisher import StatusPublisher
from cuboidtrain.train.monitor.stats import Rates, RunningStats
from cuboidtrain.train.monitor.status import FINISHED, Checkpoint, TrainerStatus, TrainingFailed, Validation
from shared.errors import UsageError
from shared.spool import foreign_names

if TYPE_CHECKING:  # the loop imports evaluation lazily: only when a validation spool is given
    from cuboidtrain.train.evaluate import Evaluation

log = logging.getLogger(__name__)

STARVING = 0.05  # data wait above this fraction of step time is a problem (docs/contract.md, "Targets")
STARVED = 0.20  # and above this one, over a full window of steps, a warning: the GPU idles (issue 29)
OUTRUN = 1.0  # mean earlier uses of a batch's samples above which the trainer outruns the generator
IDLE_LOG_EVERY = 60.0  # s between repeats of the same "no usable samples" warning


class Progress:
    """The loop's one reporter: an event method per thing that happens, a status on demand."""

    def __init__(self, config: TrainConfig, device: torch.device, watcher, dashboard=None, rank: int = 0, world: int = 1,
                 stop=None):
        """`watcher`: the spool's census (count, arrivals, evictions). `rank`, `world`: torchrun's;
        ranks other than 0 keep the figures but write nothing. `stop`: the run's StopRequest,
        which the heartbeat watches."""
        self.config, self.watcher, self.writes = config, watcher, rank == 0
        self.stats = RunningStats()
        self.metrics_log = MetricsLog(Path(config.out), self.writes)
        self.publisher = StatusPublisher(Path(config.out), dashboard, stop, self.writes)
        self.sampler = None  # the loader's EpochSampler, from begin(): where the epoch stands
        self.idle_said = (None, 0.0)  # the last "no usable samples" warning and when
        self.val_failed: str | None = None  # the last validation's failure, while no later one passed
        self.error: str | None = None  # why the run failed (state "failed"): the first of its notes
        self._status = TrainerStatus(
            phase=config.phase, phase_meaning=PHASES[config.phase], shape=config.shape, size=config.size,
            device=str(device), out=str(Path(config.out)), spool=config.spool, state=self.publisher.state,
            pid=os.getpid(), rank=rank, world_size=world, started=time.time(), updated=time.time(),
            step=0, steps_total=config.steps, epoch=0, epochs_total=config.epochs,
            batch_in_epoch=0, batches_in_epoch=0, loss_weights=list(config.loss_weights),
        )

    # ---- events from the loop

    def begin(self, step: int, sampler, kept: Checkpoint | None = None) -> None:
        """Training starts after `step`; `kept`: the checkpoint a resumed run continues, its last
        until it writes one (the dashboard's "ckpt step" showed a dash after `--resume`)."""
        self.sampler = sampler
        self._status.step = step
        self._status.last_checkpoint = kept
        self._publish(force=True)

    def state(self, state: str) -> None:
        if self.publisher.enter(state):
            self._publish(force=True)

    def fetched(self) -> float:
        """Called when a batch arrives: seconds waited for it since the last step ended."""
        return self.stats.fetched()

    def skip(self, skipped: dict) -> None:
        self.stats.skip(skipped)

    def listed(self, spool: str) -> None:
        """A new epoch's listing: count what else lies in the spool (reported, never read)."""
        if self.writes:
            try:
                self.stats.foreign = len(foreign_names(Path(spool)))
            except OSError:
                self.stats.foreign = 0

    def idle(self, reason: str, wait: float | None) -> None:
        """Nothing to train on: say why on the dashboard, and in the log when the reason
        changes or once a minute. `wait`: seconds until the next listing (None: giving up)."""
        self._status.idle = reason
        self.state("waiting for samples")
        self._publish(force=True)
        said, when = self.idle_said
        if reason != said or time.monotonic() - when > IDLE_LOG_EVERY:
            then = f"listing again in {wait:g} s" if wait is not None else "giving up"
            log.warning("%s; %s (skipped so far: %s)", reason, then, _counts(self.stats.skipped))
            self.idle_said = (reason, time.monotonic())

    def replicas(self, ranks: list[dict]) -> None:
        """Each torchrun rank's final step and weights hash: equal while the replicas agree."""
        self._status.replicas = ranks
        if self.writes and len({(r["step"], r["weights"]) for r in ranks}) > 1:
            log.error("torchrun ranks disagree at the end: %s", ranks)

    def step(self, step: int, losses: dict, samples: int, waited: float, age: float, reuse: float, skipped: dict) -> None:
        self.stats.stepped(losses, samples, waited, age, reuse, skipped)
        self._status.idle = None  # training again
        self._status.step = step
        if step % self.config.log_every == 0:
            self.metrics_log.record(step, self.sampler.where().epoch, self.stats.mean_losses(), self.stats.rates(),
                                    self.stats.freshness, dict(self.stats.skipped))
        self._publish()

    def checkpointed(self, path: Path, step: int) -> None:
        self._status.last_checkpoint = Checkpoint(str(path), step, time.time())
        self._publish(force=True)

    def validated(self, step: int, result: Evaluation) -> None:
        self.val_failed = None
        self._status.val = Validation(step, result.mean_px_error, result.median_px_error)
        self.metrics_log.validated(self._status.val)
        self._publish(force=True)

    def validation_failed(self, message: str) -> None:
        self.val_failed = message
        log.warning("%s", message)
        self._publish(force=True)

    def failed(self, exc: BaseException) -> None:
        """The run ends on `exc`: the status says `failed` and why, unless it already says how
        it ended ("gave up"). Written best-effort: the disk may be the failure."""
        if self.publisher.state in FINISHED:
            return
        message = str(exc).splitlines()[0] if str(exc) else ""
        if not isinstance(exc, (UsageError, TrainingFailed)):
            message = f"{type(exc).__name__}: {message}" if message else type(exc).__name__
        self.error = message
        self._status.idle = None
        self.publisher.enter("failed")
        if self.sampler is None:
            return  # failed before begin(): nothing to count
        try:
            self._publish(force=True)
        except OSError as err:
            log.warning("%s: cannot write status.json (%s)", self.config.out, err.strerror or err)

    # ---- figures

    def metrics(self) -> dict:
        """The smoothed losses and the rates, as a checkpoint stores them."""
        return {**self.stats.smoothed, **asdict(self.stats.rates())}

    def snapshot(self) -> TrainerStatus:
        """The status now (a copy: later events do not change it)."""
        where, rates = self.sampler.where(), self.stats.rates()
        self._status.update(
            **asdict(rates),
            state=self.publisher.state,
            updated=time.time(),
            epoch=where.epoch,
            batch_in_epoch=where.taken,
            batches_in_epoch=where.batches,
            losses=dict(self.stats.smoothed),
            loss_history={k: list(v) for k, v in self.stats.history.items()},
            freshness=self.stats.freshness,
            skipped=dict(self.stats.skipped),
            spool_samples=self.watcher.count,
            # samples the generator evicted before this trainer read them (cuboidtrain.data.census)
            spool_evicted_unread=getattr(self.watcher, "evicted_unread_total", None),
            foreign_files=self.stats.foreign,
            eta_s=self._eta(rates.step_time_s, where),
            notes=self._notes(rates),
        )
        return replace(self._status)

    def status(self) -> dict:
        """The status now, as status.json holds it."""
        return self.snapshot().to_json()

    def _eta(self, step_time: float | None, where: EpochPosition) -> float | None:
        if step_time is None or (self.config.steps is None and self.config.epochs is None):
            return None
        if self.config.steps is not None:
            return max(0, self.config.steps - self._status.step) * step_time
        remaining = (self.config.epochs - where.epoch - 1) * where.batches + (where.batches - where.taken)
        return max(0, remaining) * step_time

    def _notes(self, rates: Rates) -> list[str]:
        notes = [m for m in (self.error, self._status.idle, self.val_failed) if m]
        wait, skipped, foreign = rates.data_wait_fraction, self.stats.skipped, self.stats.foreign
        if wait is not None and wait > STARVED and self.stats.window_full():
            notes.append(f"warning: data wait {wait:.0%} of step time stays above {STARVED:.0%}: the device idles "
                         "waiting for the loader (more --loader-workers, fewer generator workers on the same cores)")
        elif wait is not None and wait > STARVING and self.stats.window_full():
            notes.append(f"data wait {wait:.0%} of step time: the loader is starving (more --loader-workers, or a faster spool disk)")
        reuse = self.stats.freshness.mean_reuse
        if reuse is not None and reuse > OUTRUN:
            notes.append(f"samples reused {reuse:.1f} times on average: training outruns the generator, and the "
                         "spool's reuse feeds it (paper 3.3.2), not a faster generator; a larger cuboidgen --limit varies it")
        if skipped["other_size"]:
            notes.append(f"{skipped['other_size']} samples of another size skipped: run cuboidgen with --size {self.config.size}")
        if skipped["other_shape"]:
            notes.append(f"{skipped['other_shape']} samples of another shape skipped (a mix spool, or the wrong --shape)")
        if skipped["damaged"]:
            notes.append(f"{skipped['damaged']} damaged samples skipped: their bytes changed after writing (a failing "
                         f"disk or copy; cuboidgen inspect {self.config.spool} counts them)")
        if skipped["corrupt"]:
            notes.append(f"{skipped['corrupt']} corrupt samples skipped (cuboidgen inspect {self.config.spool} counts them)")
        if foreign:
            notes.append(f"{foreign} foreign files in the spool (not samples): ignored")
        return notes

    # ---- outputs

    def _publish(self, force: bool = False) -> None:
        if self.publisher.due(force):
            self._status.spool_arrivals_per_s = self.watcher.arrivals_per_s()
            self.publisher.show(self.snapshot())

    def __enter__(self) -> "Progress":
        self.publisher.__enter__()
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if exc is not None:
            self.failed(exc)
        self.publisher.__exit__(kind, exc, tb)
        self.metrics_log.close()


def _counts(counter: Counter) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {n}" for k, n in counter.items() if n) or "none"
