"""When training stops or waits: the stop SIGTERM and Ctrl-C ask for, a run's end, the backing-off wait on an unusable spool."""
from __future__ import annotations

import contextlib
import os
import signal
import time
from dataclasses import dataclass

from cuboidtrain.train.config import TrainConfig

IDLE_WAIT = (0.5, 30.0)  # s: first and longest pause between listings of a spool with no usable sample


class StopRequest:
    """Set by SIGTERM or SIGINT; the loop checks it between steps.

    Python runs a signal's handler in the main thread, between bytecodes: not while that
    thread is inside a step's backward pass, which can take seconds. `asked` sees the
    signal at once, from any thread, through the wakeup file the signal module writes
    the signal's number to (installed() sets it up), so the dashboard can say
    "stopping after this step" while the step is still running."""

    STOPS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signal: int | None = None
        self._wakeup: int | None = None  # the read end of the signal module's wakeup pipe
        self._woken = False

    def __bool__(self) -> bool:
        return self.signal is not None

    def asked(self) -> bool:
        """Whether a stop was asked for, even one whose handler has not run yet."""
        if self.signal is not None or self._woken:
            return True
        if self._wakeup is not None:
            try:
                self._woken = any(b in self.STOPS for b in os.read(self._wakeup, 64))
            except (BlockingIOError, OSError):
                pass
        return self._woken

    @contextlib.contextmanager
    def installed(self):
        handler = lambda signum, frame: setattr(self, "signal", signum)  # noqa: E731
        previous = {s: signal.signal(s, handler) for s in self.STOPS}
        read, write = os.pipe()
        os.set_blocking(read, False)
        os.set_blocking(write, False)
        wakeup = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        self._wakeup = read
        try:
            yield self
        finally:
            signal.set_wakeup_fd(wakeup)
            self._wakeup = None
            os.close(read)
            os.close(write)
            for s, h in previous.items():
                signal.signal(s, h)


def leave_signals_to_main(_worker_id: int) -> None:
    """A loader worker's start: it ignores SIGINT and SIGTERM, which the main process decides on."""
    # Ctrl-C reaches the whole process group, and systemd or `pkill -f` send SIGTERM to
    # every process: the main process decides when to stop (after a checkpoint), so a
    # loader worker must not die under it. Workers exit on their own when main is gone.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def finished(config: TrainConfig, step: int, epoch: int, started: float | None = None) -> bool:
    """Whether --steps, --stop-at, --epochs or --max-minutes are done after `step`, in epoch `epoch`."""
    if config.stop_at is not None and step >= config.stop_at:
        return True
    if config.max_minutes is not None and started is not None and time.monotonic() - started > config.max_minutes * 60:
        return True
    if config.steps is not None:
        return step >= config.steps
    return config.epochs is not None and epoch >= config.epochs


def next_wait(wait: float) -> float:
    """The pause after `wait` while the spool stays unusable: doubled, at most IDLE_WAIT[1]."""
    return min(2 * wait, IDLE_WAIT[1])


def idle_pause(seconds: float, stop) -> None:
    """Sleep between listings, waking early when a stop is asked for."""
    deadline = time.monotonic() + seconds
    while not stop and time.monotonic() < deadline:
        time.sleep(min(0.1, max(deadline - time.monotonic(), 0)))


@dataclass(frozen=True)
class Backoff:
    """The wait between listings that gave nothing to train on: the next pause, and since when
    (monotonic s) no listing was usable, None while training goes on."""

    wait: float = IDLE_WAIT[0]
    idle_since: float | None = None

    def after(self, since: float) -> "Backoff":
        """The backoff once this pause is taken, idle since `since`."""
        return Backoff(next_wait(self.wait), since)


def unusable_reason(config: TrainConfig, skipped: dict) -> str:
    """Why the last listing gave nothing to train on, with what would fix it."""
    counts = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in skipped.items() if n) or "none read"
    reason = f"spool {config.spool}: no usable sample in the last listing ({counts})"
    if skipped.get("other_size"):
        reason += f"; samples of another size need --reframe, or a generator with --size {config.size}"
    elif skipped.get("other_shape"):
        reason += f"; the spool holds no {config.shape} samples (--shape)"
    elif skipped.get("damaged"):
        reason += "; their bytes changed after writing (cuboidgen inspect names the fault)"
    return reason
