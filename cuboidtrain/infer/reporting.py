"""How far `cuboidtrain infer` is: a rich bar on a terminal, a log line every few seconds without one,
and a summary at the end. The counting (`Tally`) is apart from the showing, so tests read it.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

from cuboidtrain.fit.fitter import FitFailure, Outcome

log = logging.getLogger(__name__)

LOG_SECONDS = 5.0  # between plain progress lines


@dataclass
class Tally:
    """Inputs and their outcomes counted as they complete (the records OUT already held apart)."""

    total: int  # inputs of the run, resumed ones included
    resumed: int = 0  # inputs OUT already held
    done: int = 0  # inputs tried this run, failed ones included
    failed: int = 0  # inputs whose first record has an error (this run and resumed)
    failed_now: int = 0  # of them, the inputs tried this run
    shapes: Counter = field(default_factory=Counter)  # records by shape class ("failed" for errors)
    stopped: str | None = None  # what stopped the run before its end ("Ctrl-C", "SIGTERM"), if anything
    started: float = field(default_factory=time.monotonic)

    def add(self, outcomes: Sequence[Outcome]) -> None:
        """An input fitted this run: its outcomes (a FitFailure is a failed input)."""
        self.done += 1
        failed = bool(outcomes) and isinstance(outcomes[0], FitFailure)
        self.failed_now += failed
        self.count([None if isinstance(o, FitFailure) else o.shape for o in outcomes], failed)

    def resume(self, records: Sequence[dict]) -> None:
        """An input OUT already held: its records, as read back."""
        self.resumed += 1
        self.count([r["shape"] for r in records], bool(records) and records[0]["error"] is not None)

    def count(self, shapes: list[str | None], failed: bool) -> None:
        self.failed += failed
        self.shapes.update(shape or "failed" for shape in shapes)

    @property
    def fitted(self) -> int:
        """Inputs fitted this run: those tried, less those that failed (the summary's counts add up)."""
        return self.done - self.failed_now

    @property
    def rate(self) -> float:
        return self.done / max(time.monotonic() - self.started, 1e-9)

    def line(self) -> str:
        finished = self.resumed + self.done
        left = self.total - finished
        eta = f"ETA {left / self.rate:.0f} s" if self.rate > 0 else "ETA ?"
        return (f"{finished}/{self.total} masks, {self.rate:.1f} masks/s, {eta}, "
                f"{self.failed} failure{'' if self.failed == 1 else 's'}")

    def summary(self) -> str:
        seconds = time.monotonic() - self.started
        shapes = ", ".join(f"{name} {n}" for name, n in sorted(self.shapes.items()) if name != "failed") or "none"
        resumed = f" ({self.resumed} already in OUT)" if self.resumed else ""
        count = f"stopped by {self.stopped}: {self.resumed + self.done} of {self.total}" if self.stopped else \
            f"{self.resumed + self.done}"
        return (f"{count} masks{resumed}; fitted {self.fitted} in {seconds:.1f} s "
                f"({self.rate:.1f} masks/s); records by shape: {shapes}; {self.failed} failed")


class Reporter:
    """Shows a Tally: `with Reporter(tally, console) as show: ...; show.update()` per input."""

    def __init__(self, tally: Tally, console):
        self.tally, self.console = tally, console
        self.bar = None
        self.logged = time.monotonic()

    def __enter__(self) -> "Reporter":
        if self.console.is_terminal:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self.bar = Progress(TextColumn("fitting"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[rate]:.1f} masks/s"), TimeRemainingColumn(),
                                TimeElapsedColumn(), TextColumn("{task.fields[failed]} failed"),
                                console=self.console, transient=False)
            self.bar.start()
            self.task = self.bar.add_task("fit", total=self.tally.total, completed=self.tally.resumed,
                                          rate=0.0, failed=self.tally.failed)
        return self

    def update(self) -> None:
        tally = self.tally
        if self.bar is not None:
            self.bar.update(self.task, completed=tally.resumed + tally.done, rate=tally.rate, failed=tally.failed)
        elif time.monotonic() - self.logged >= LOG_SECONDS:
            self.logged = time.monotonic()
            log.info("%s", tally.line())

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.update()
            self.bar.stop()
        if self.tally.total > 1 or self.tally.stopped:  # one mask's run is its record
            self.console.print(self.tally.summary(), highlight=False, soft_wrap=True)
