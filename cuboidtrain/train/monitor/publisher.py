"""The trainer's status publisher: writes each status to OUT/status.json and the dashboard, with a heartbeat between.

The loop publishes at most once a second (`due`), so reporting costs nothing
next to a step. A heartbeat thread republishes the last status every second
while a step runs (a step can take many seconds on a CPU), so `watch` sees a
live trainer, and shows "stopping after this step" as soon as SIGTERM or
Ctrl-C arrives.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from cuboidtrain.train.monitor.status import TrainerStatus, write_status

log = logging.getLogger(__name__)

PUBLISH_EVERY = 1.0  # s
HEARTBEAT_EVERY = 0.25  # s between the heartbeat's looks at the clock and the stop request
STOPPING = "stopping after this step"
STOPPABLE = ("training", "waiting for samples")  # the states a stop request turns into STOPPING


class StatusPublisher:
    """Publishes the run's status and keeps its state (starting, training, ..., done).

    `writes` False (torchrun ranks other than 0): keeps the state, writes nothing.
    `stop`: the run's StopRequest, which the heartbeat watches."""

    def __init__(self, out: Path, dashboard=None, stop=None, writes: bool = True):
        self.out, self.dashboard, self.stop, self.writes = Path(out), dashboard, stop, writes
        self.state = "starting"
        self._lock = threading.Lock()  # one writer of status.json and the dashboard at a time
        self._published: TrainerStatus | None = None  # the last status written, which the heartbeat refreshes
        self._beating = threading.Event()
        self._heart: threading.Thread | None = None
        self.last_publish = 0.0  # the loop's last publish: throttles the loop alone
        self.last_shown = 0.0  # the last status written by anyone: the heartbeat fills the gaps after it

    def enter(self, state: str) -> bool:
        """Moves to `state`; whether it changed. After a stop request the step in hand is the
        last: training and waiting no longer replace "stopping after this step"."""
        if self.state == STOPPING and state in STOPPABLE:
            return False
        if state == self.state:
            return False
        self.state = state
        return True

    def due(self, force: bool = False) -> bool:
        """Whether the loop should publish now: forced, or a second since its last publish
        (which this call counts as one); never on a rank that writes nothing."""
        now = time.monotonic()
        if not force and now - self.last_publish < PUBLISH_EVERY:
            return False
        self.last_publish = now
        return self.writes

    def show(self, status: TrainerStatus) -> None:
        """Writes `status` to status.json and hands it to the dashboard."""
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
        stopping = self.stop is not None and self.stop.asked() and last.state in STOPPABLE
        if stopping:
            self.state = STOPPING
        elif time.monotonic() - self.last_shown < PUBLISH_EVERY:
            return
        # The loop's own throttle (last_publish) is left alone: a beat between two slow steps
        # must not make the loop skip publishing the step that follows it.
        self.show(last.refreshed(state=self.state))

    def _heartbeat(self) -> None:
        while not self._beating.wait(HEARTBEAT_EVERY):
            try:
                self.beat()
            except Exception:  # a full disk, say: the loop's own writes will say so
                log.debug("heartbeat", exc_info=True)

    def __enter__(self) -> "StatusPublisher":
        if self.writes:
            self._heart = threading.Thread(target=self._heartbeat, name="progress-heartbeat", daemon=True)
            self._heart.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._heart is not None:
            self._beating.set()
            self._heart.join()
