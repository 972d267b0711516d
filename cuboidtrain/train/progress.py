"""What a training run reports: the status (dashboard, `OUT/status.json`), metrics.jsonl, TensorBoard.

The loop tells `Progress` what happened (a batch fetched, a step taken, a
checkpoint written); Progress keeps the running figures and publishes them at
most once a second, so reporting costs nothing next to a step. A heartbeat
thread republishes the last figures every second while a step runs (a step can
take many seconds on a CPU), so `watch` sees a live trainer, and shows
"stopping after this step" as soon as SIGTERM or Ctrl-C arrives.
"""
from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter, deque
from dataclasses import asdict, replace
from pathlib import Path

import torch

from cuboidtrain.train.config import PHASES, TrainConfig
from cuboidtrain.train.data import SKIP_REASONS
from cuboidtrain.train.status import Checkpoint, Freshness, TrainerStatus, Validation, write_status
from shared.spool import foreign_names

log = logging.getLogger(__name__)

WINDOW = 20  # steps over which rates and the data-wait fraction are measured
HISTORY = 120  # loss values kept for the dashboard's trend
EMA = 0.1  # weight of the newest loss in the smoothed value
STARVING = 0.05  # data wait above this fraction of step time is a problem (docs/contract.md, "Targets")
PUBLISH_EVERY = 1.0  # s
HEARTBEAT_EVERY = 0.25  # s between the heartbeat's looks at the clock and the stop request
STOPPING = "stopping after this step"
IDLE_LOG_EVERY = 60.0  # s between repeats of the same "no usable samples" warning


def tensorboard_writer(out: Path):
    """A SummaryWriter when tensorboard is installed, else None (it is optional)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tensorboard"))


class Progress:
    def __init__(self, config: TrainConfig, device: torch.device, watcher, dashboard=None, rank: int = 0, world: int = 1,
                 stop=None):
        """`rank`, `world`: torchrun's; ranks other than 0 keep the figures but write nothing.
        `stop`: the run's StopRequest, which the heartbeat watches."""
        self.config, self.out, self.watcher, self.dashboard = config, Path(config.out), watcher, dashboard
        self.stop = stop
        self._lock = threading.Lock()  # one writer of status.json and the dashboard at a time
        self._published: TrainerStatus | None = None  # the last status written, which the heartbeat refreshes
        self._beating = threading.Event()
        self._heart: threading.Thread | None = None
        self.writes = rank == 0
        self.tensorboard = tensorboard_writer(self.out) if self.writes else None
        self.foreign = 0  # files in the spool that are not samples (ignored)
        self.idle_said = (None, 0.0)  # the last "no usable samples" warning and when
        self.smoothed: dict[str, float] = {}
        self.history = {k: deque(maxlen=HISTORY) for k in ("D_R", "D_S", "D_T", "total")}
        self.recent = deque(maxlen=WINDOW)  # (samples, waited s, step s) per step
        self.logged = {"losses": Counter(), "steps": 0}  # sums since the last metrics record
        self.skipped = Counter(dict.fromkeys(SKIP_REASONS, 0))
        self.freshness = {"mean_age_s": None, "mean_reuse": None}
        self.last_end = time.perf_counter()
        self.last_publish = 0.0  # the loop's last publish: throttles the loop alone
        self.last_shown = 0.0  # the last status written by anyone: the heartbeat fills the gaps after it
        self._status = TrainerStatus(
            phase=config.phase, phase_meaning=PHASES[config.phase], shape=config.shape, size=config.size,
            device=str(device), out=str(self.out), spool=config.spool, state="starting",
            pid=os.getpid(), rank=rank, world_size=world, started=time.time(), updated=time.time(),
            step=0, steps_total=config.steps, epoch=0, epochs_total=config.epochs,
            batch_in_epoch=0, batches_in_epoch=0, loss_weights=list(config.loss_weights),
        )

    # ---- events from the loop

    def begin(self, step: int, sampler) -> None:
        self.sampler = sampler
        self._status.step = step
        self._publish(force=True)

    def state(self, state: str) -> None:
        if self._status.state == STOPPING and state in ("training", "waiting for samples"):
            return  # a stop was asked for: the step in hand is the last
        if state != self._status.state:
            self._status.state = state
            self._publish(force=True)

    def fetched(self) -> float:
        """Called when a batch arrives: seconds waited for it since the last step ended."""
        self.fetch_time = time.perf_counter()
        return self.fetch_time - self.last_end

    def skip(self, skipped: dict) -> None:
        self.skipped.update(skipped)

    def listed(self, spool: str) -> None:
        """A new epoch's listing: count what else lies in the spool (reported, never read)."""
        if self.writes:
            try:
                self.foreign = len(foreign_names(Path(spool)))
            except OSError:
                self.foreign = 0

    def idle(self, reason: str, wait: float | None) -> None:
        """Nothing to train on: say why on the dashboard, and in the log when the reason
        changes or once a minute. `wait`: seconds until the next listing (None: giving up)."""
        self._status.idle = reason
        self.state("waiting for samples")
        self._publish(force=True)
        said, when = self.idle_said
        if reason != said or time.monotonic() - when > IDLE_LOG_EVERY:
            then = f"listing again in {wait:g} s" if wait is not None else "giving up"
            log.warning("%s; %s (skipped so far: %s)", reason, then, _counts(self.skipped))
            self.idle_said = (reason, time.monotonic())

    def replicas(self, ranks: list[dict]) -> None:
        """Each torchrun rank's final step and weights hash: equal while the replicas agree."""
        self._status.replicas = ranks
        if self.writes and len({(r["step"], r["weights"]) for r in ranks}) > 1:
            log.error("torchrun ranks disagree at the end: %s", ranks)

    def step(self, step: int, losses: dict, samples: int, waited: float, age: float, reuse: float, skipped: dict) -> None:
        now = time.perf_counter()
        self.recent.append((samples, waited, now - self.last_end))
        self.last_end = now
        self.skipped.update(skipped)
        self._status.idle = None  # training again
        self.freshness = {"mean_age_s": age, "mean_reuse": reuse}
        for key, value in losses.items():
            previous = self.smoothed.get(key, value)
            self.smoothed[key] = previous + EMA * (value - previous)
            self.history[key].append(value)
        self.logged["losses"].update(losses)
        self.logged["steps"] += 1
        self._status.step = step
        if step % self.config.log_every == 0:
            self._record(step)
        self._publish()

    def checkpointed(self, path: Path, step: int) -> None:
        self._status.last_checkpoint = Checkpoint(str(path), step, time.time())
        self._publish(force=True)

    def validated(self, step: int, result: dict) -> None:
        self._status.val = Validation(step, result["mean_px_error"], result["median_px_error"])
        self._write_metrics({"step": step, "time": time.time(), "val": asdict(self._status.val)})
        if self.tensorboard is not None:
            self.tensorboard.add_scalar("val/mean_px_error", result["mean_px_error"], step)
        self._publish(force=True)

    # ---- figures

    def rates(self) -> dict:
        samples = sum(r[0] for r in self.recent)
        total = sum(r[2] for r in self.recent)
        waited = sum(r[1] for r in self.recent)
        return {
            "samples_per_s": samples / total if total else None,
            "step_time_s": total / len(self.recent) if self.recent else None,
            "data_wait_fraction": waited / total if total else None,
        }

    def metrics(self) -> dict:
        return {**self.smoothed, **self.rates()}

    def snapshot(self) -> TrainerStatus:
        """The status now (a copy: later events do not change it)."""
        s = self.sampler.state
        rates = self.rates()
        self._status.update(
            **rates,
            updated=time.time(),
            epoch=s.epoch,
            batch_in_epoch=s.position,
            batches_in_epoch=len(self.sampler),
            losses=dict(self.smoothed),
            loss_history={k: list(v) for k, v in self.history.items()},
            freshness=Freshness(**self.freshness),
            skipped=dict(self.skipped),
            spool_samples=self.watcher.count,
            # samples the generator evicted before this trainer read them (cuboidtrain.train.spoolwatch)
            spool_evicted_unread=getattr(self.watcher, "evicted_unread_total", None),
            foreign_files=self.foreign,
            eta_s=self._eta(rates["step_time_s"]),
            notes=self._notes(rates),
        )
        return replace(self._status)

    def status(self) -> dict:
        """The status now, as status.json holds it."""
        return self.snapshot().to_json()

    def _eta(self, step_time: float | None) -> float | None:
        if step_time is None or (self.config.steps is None and self.config.epochs is None):
            return None
        if self.config.steps is not None:
            return max(0, self.config.steps - self._status.step) * step_time
        s, per_epoch = self.sampler.state, len(self.sampler)
        remaining = (self.config.epochs - s.epoch - 1) * per_epoch + (per_epoch - s.position)
        return max(0, remaining) * step_time

    def _notes(self, rates: dict) -> list[str]:
        notes = [self._status.idle] if self._status.idle else []
        wait = rates["data_wait_fraction"]
        if wait is not None and wait > STARVING and len(self.recent) == WINDOW:
            notes.append(f"data wait {wait:.0%} of step time: the loader is starving (more --loader-workers, or a faster spool disk)")
        if self.skipped["other_size"]:
            notes.append(f"{self.skipped['other_size']} samples of another size skipped: run cuboidgen with --size {self.config.size}")
        if self.skipped["other_shape"]:
            notes.append(f"{self.skipped['other_shape']} samples of another shape skipped (a mix spool, or the wrong --shape)")
        if self.skipped["corrupt"]:
            notes.append(f"{self.skipped['corrupt']} corrupt samples skipped (cuboidgen inspect {self.config.spool} counts them)")
        if self.foreign:
            notes.append(f"{self.foreign} foreign files in the spool (not samples): ignored")
        return notes

    # ---- outputs

    def _record(self, step: int) -> None:
        n = max(self.logged["steps"], 1)
        record = {"step": step, "epoch": self.sampler.state.epoch, "time": time.time(),
                  **{k: v / n for k, v in self.logged["losses"].items()}, **self.rates(),
                  **self.freshness, "skipped": dict(self.skipped)}
        self.logged = {"losses": Counter(), "steps": 0}
        self._write_metrics(record)
        if self.tensorboard is not None:
            for key in ("D_R", "D_S", "D_T", "total", "samples_per_s", "data_wait_fraction"):
                if record.get(key) is not None:
                    self.tensorboard.add_scalar(key if key.startswith("D_") or key == "total" else f"speed/{key}",
                                                record[key], step)

    def _write_metrics(self, record: dict) -> None:
        if not self.writes:
            return
        with open(self.out / "metrics.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")

    def _publish(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last_publish < PUBLISH_EVERY:
            return
        self.last_publish = now
        if not self.writes:
            return
        self._status.spool_arrivals_per_s = self.watcher.arrivals_per_s()
        self._show(self.snapshot())

    def _show(self, status: TrainerStatus) -> None:
        with self._lock:
            self._published = status
            self.last_shown = time.monotonic()
            write_status(self.out, status)
            if self.dashboard is not None:
                self.dashboard.update(status)

    def beat(self) -> None:
        """The heartbeat: the last status again, dated now (and, once a stop was asked for,
        in state "stopping after this step"), when the loop has published nothing for a second."""
        last = self._published
        if last is None:
            return
        stopping = self.stop is not None and self.stop.asked() and last.state in ("training", "waiting for samples")
        if stopping:
            self._status.state = STOPPING
        elif time.monotonic() - self.last_shown < PUBLISH_EVERY:
            return
        # The loop's own throttle (last_publish) is left alone: a beat between two slow steps
        # must not make the loop skip publishing the step that follows it.
        self._show(last.refreshed(state=self._status.state))

    def _heartbeat(self) -> None:
        while not self._beating.wait(HEARTBEAT_EVERY):
            try:
                self.beat()
            except Exception:  # a full disk, say: the loop's own writes will say so
                log.debug("heartbeat", exc_info=True)

    def __enter__(self) -> "Progress":
        if self.writes:
            self._heart = threading.Thread(target=self._heartbeat, name="progress-heartbeat", daemon=True)
            self._heart.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._heart is not None:
            self._beating.set()
            self._heart.join()
        if self.tensorboard is not None:
            self.tensorboard.close()


def _counts(counter: Counter) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {n}" for k, n in counter.items() if n) or "none"
