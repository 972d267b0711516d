"""Ctrl-C and SIGTERM during `infer`: no new input starts, the ones in hand finish, what was fitted is written.

`Stop.installed()` sets the handlers for the fitting phase only (before it, Ctrl-C ends the
command at once: nothing was fitted). The first signal is a request, read between inputs
(`pool.fit_groups`, `batch.run_batch`); a second one is a KeyboardInterrupt, at once: a fit
that hangs can still be stopped, and a `--jsonl` store keeps its whole lines as it always does.
The command then exits 128 + the signal's number: 130 for Ctrl-C, 143 for SIGTERM.
"""
from __future__ import annotations

import contextlib
import logging
import signal
import threading

log = logging.getLogger(__name__)

NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


class Stop:
    """Whether a stop was asked for (`bool(stop)`), and by which signal."""

    def __init__(self):
        self.signal: int | None = None

    def __bool__(self) -> bool:
        return self.signal is not None

    @property
    def name(self) -> str:
        return NAMES.get(self.signal, f"signal {self.signal}")

    @property
    def exit_code(self) -> int:
        """The exit status of a command a signal stopped, as a shell reports it: 128 + its number."""
        return 128 + int(self.signal or 0)

    def _handle(self, signum: int, _frame) -> None:
        if self.signal is not None:  # the second: at once
            raise KeyboardInterrupt
        self.signal = signum
        log.warning("%s: finishing the inputs in hand, then writing what was fitted (again: stop at once)",
                    self.name)

    @contextlib.contextmanager
    def installed(self):
        """The handlers, while the block runs; a no-op outside the main thread (signals go there)."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        previous = {s: signal.signal(s, self._handle) for s in NAMES}
        try:
            yield self
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)


@contextlib.contextmanager
def held_during_import():
    """Ctrl-C and SIGTERM held while the block imports a native library, and delivered when it ends, at a
    safe point: a KeyboardInterrupt raised inside torch's pybind11 initialisation is thrown through C++
    (`pybind11::error_already_set`) and ends the interpreter by std::terminate (exit -6, a C++ message
    on stderr; tests/test_infer_stop.py saw it once in some runs). A no-op outside the main thread."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, set(NAMES))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def leave_signals_to_parent() -> None:
    """A `--workers` process's start: Ctrl-C reaches the whole process group, and a service manager
    sends SIGTERM to every process; the parent decides, and finishes the inputs in hand."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
