"""The generator's dashboard: a rich table when stdout is a terminal, log lines otherwise.

The daemon hands a `GenSnapshot` to `Dashboard.update`; rendering is a pure
function of the snapshot so it can be tested as text.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field

from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table

from shared.console import ECHO_ROOM

log = logging.getLogger(__name__)


@dataclass
class WorkerView:
    published: int
    evicted: int
    errors: int
    rate: float  # samples/s over the last interval
    state: str  # running | disk full, backing off | stopping | done | stopped | failed: cannot write


@dataclass
class GenSnapshot:
    elapsed: float  # s since start
    workers: list[WorkerView]
    spool: str
    spool_samples: int
    spool_bytes: int
    limit: int
    max_samples: int | None
    oldest_age: float | None  # s
    newest_age: float | None  # s
    size: int = 256
    shape: str = "box"
    scene: str = "paper"
    notes: list[str] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return sum(w.rate for w in self.workers)

    @property
    def published(self) -> int:
        return sum(w.published for w in self.workers)

    @property
    def evicted(self) -> int:
        return sum(w.evicted for w in self.workers)

    @property
    def errors(self) -> int:
        return sum(w.errors for w in self.workers)


def human_bytes(n: float) -> str:
    """Bytes in binary units, named as such: 1 KiB = 1024 B."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def human_age(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 120:
        return f"{seconds:.1f} s"
    return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def render(s: GenSnapshot, width: int | None = None) -> Panel:
    """The dashboard for one snapshot; `width` in columns (None: the console's)."""
    workers = Table("worker", "samples/s", "published", "evicted", "errors", "state", box=None, expand=True)
    for i, w in enumerate(s.workers):
        style = "red" if w.errors else ("yellow" if w.state != "running" else "")
        workers.add_row(str(i), f"{w.rate:,.0f}", f"{w.published:,}", f"{w.evicted:,}", str(w.errors), w.state, style=style)
    workers.add_row("all", f"{s.rate:,.0f}", f"{s.published:,}", f"{s.evicted:,}", str(s.errors), "", style="bold")
    limit = f"{s.limit:,}" if s.limit else "retained (no limit)"
    target = f" of {s.max_samples:,}" if s.max_samples else ""
    spool = Table.grid(padding=(0, 2))
    spool.add_row("spool", s.spool, "samples", f"{s.spool_samples:,} / {limit}")
    mean = s.spool_bytes / s.spool_samples if s.spool_samples else 0
    spool.add_row("bytes", f"{human_bytes(s.spool_bytes)} ({human_bytes(mean)}/sample)", "published", f"{s.published:,}{target}")
    spool.add_row("oldest", human_age(s.oldest_age), "newest", human_age(s.newest_age))
    spool.add_row("sample", f"{s.shape} {s.size}x{s.size}, scene {s.scene}", "uptime", human_age(s.elapsed))
    parts = [spool, workers] + [f"[yellow]{note}" for note in s.notes]
    return Panel(Group(*parts), title="cuboidgen", subtitle="Ctrl-C stops cleanly", width=width)


def log_line(s: GenSnapshot) -> str:
    """The same figures as one plain line, for logs and non-terminals."""
    parts = [
        f"{s.rate:,.0f} samples/s",
        f"published {s.published:,}" + (f"/{s.max_samples:,}" if s.max_samples else ""),
        f"spool {s.spool_samples:,}/{s.limit or 'retained'} ({human_bytes(s.spool_bytes)})",
        f"evicted {s.evicted:,}",
        f"errors {s.errors}",
        f"oldest {human_age(s.oldest_age)} newest {human_age(s.newest_age)}",
    ]
    states = Counter(w.state for w in s.workers)
    if set(states) != {"running"}:  # the usual state goes without saying
        parts.append("workers " + ", ".join(f"{n} {state}" for state, n in states.items()))
    return " | ".join(parts + s.notes)


class Dashboard:
    """Live rich panel, or a log line every `log_every` seconds without one."""

    def __init__(self, live: bool, log_every: float = 10.0, console: Console | None = None):
        self.console = console or Console()
        self.live = Live(console=self.console, refresh_per_second=4) if live and self.console.is_terminal else None
        self.log_every = log_every
        self._last_log: float | None = None  # nothing logged yet: the first update logs

    def __enter__(self) -> "Dashboard":
        if self.live:
            self.live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.live:
            self.live.__exit__(*exc)

    def due(self, final: bool = False) -> bool:
        """Whether an update would be shown now: lets the caller skip building a snapshot
        (a scan of the spool) that no one would see."""
        return (bool(self.live) or final or self._last_log is None
                or time.monotonic() - self._last_log >= self.log_every)

    def update(self, snapshot: GenSnapshot, final: bool = False) -> None:
        if self.live:
            self.live.update(render(snapshot, width=max(self.console.width - ECHO_ROOM, 40)), refresh=final)
        elif self.due(final):
            self._last_log = time.monotonic()
            log.info("%s", log_line(snapshot))
