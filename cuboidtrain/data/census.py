"""The spool as the trainer's dashboard shows it: how many samples, how fast they arrive,
and how many were evicted before the trainer read them. From listings alone, no watcher.

Why no watcher (issue 14): watchdog's inotify observer ran a thread in the trainer's
process that took the GIL for every publish and every eviction. Beside a generator at
full speed that thread held the GIL in every profiler sample, the trainer fell to one
step per 1.5-2 minutes, and the kernel's event queue still overflowed. The trainer lists
the spool at every epoch's start anyway, and a sample's name says which writer published
it and that writer's sequence number (`<time_ns>-<host>-<pid>-<token>-<seq>.cub`), so two
listings tell how many samples each writer published between them, including those
published and evicted before either listing saw them. Between epochs `arrivals_per_s`
lists again at most every `refresh_every` seconds: a few milliseconds of the main thread
for 10,000 names (benchmarks/soak/bench_spool_live.py measures both).

Evicted unread, the samples the paper says the trainer never misses, counted at each
epoch's listing against the one before (a sample read in an earlier epoch is not counted):
* never listed: published and evicted between two epoch listings (sequence numbers);
* listed unread: in the last listing, never read (gone when the loader came to it, or
  left by a stale epoch that ended early), and gone now.
Under torchrun only rank 0 counts, and it takes the other ranks' shares as read.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

from shared.spool import SUFFIX, enumerate_spool

log = logging.getLogger(__name__)

REFRESH_EVERY = 30.0  # s: the longest the dashboard's count and rate go without a listing
MIN_WINDOW = 5.0  # s: a rate over a shorter span than this is noise; keep counting


def parse_name(name: str) -> tuple[str, int] | None:
    """(writer, sequence number) of a sample's name; None for a name of another form (copied in)."""
    head, _, seq = name[: -len(SUFFIX)].rpartition("-")
    _, _, writer = head.partition("-")
    if not writer or not seq.isdigit():
        return None
    return writer, int(seq)


def highest_sequences(names: list[str]) -> dict[str, int]:
    """Each writer's highest sequence number among `names`."""
    highest: dict[str, int] = {}
    for name in names:
        parsed = parse_name(name)
        if parsed is not None and parsed[1] > highest.get(parsed[0], 0):
            highest[parsed[0]] = parsed[1]
    return highest


def published_between(before: dict[str, int], after: dict[str, int]) -> int:
    """Samples published between two listings, from each writer's highest sequence number.
    A writer that `before` does not know counts from its first sample (it started since)."""
    return sum(seq - before.get(writer, 0) for writer, seq in after.items() if seq > before.get(writer, 0))


class SpoolCensus:
    """The trainer's view of the spool, fed by its epoch listings (`listed`); `count` and
    `arrivals_per_s()` are what `Progress` shows. Single-threaded: the training loop's."""

    def __init__(self, spool: str | Path, refresh_every: float = REFRESH_EVERY, clock=time.monotonic,
                 list_spool=enumerate_spool):
        if refresh_every <= 0:
            raise ValueError(f"refresh_every {refresh_every}: expected a positive number of seconds")
        self.spool, self.refresh_every, self.clock, self.list_spool = Path(spool), refresh_every, clock, list_spool
        self.count = 0
        self.rate: float | None = None  # samples published per second over the latest window
        self.evicted_unread = {"never_listed": 0, "listed_unread": 0}
        self._window: tuple[float, dict[str, int]] | None = None  # start of the rate's window
        self._looked = -float("inf")
        self._last_names: list[str] = []
        self._read: set[str] = set()  # names the loader read, among the last listing's
        self._look(self._safe_listing())
        self._known = highest_sequences(self._last_names)  # highest sequence per writer at the last listing
        self._listed = set(self._last_names)

    # ---- events from the training loop

    def listed(self, names: list[str]) -> dict[str, int]:
        """An epoch's listing: re-anchor the count and rate, and count the samples evicted
        unread since the last one. Returns those counts (never listed, listed unread)."""
        self._look(names)
        current = set(names)
        new = 0
        for name in names:
            parsed = parse_name(name)
            if parsed is not None and parsed[1] > self._known.get(parsed[0], 0):
                new += 1
        merged = {**self._known, **highest_sequences(names)}  # a writer whose samples all went keeps its number
        gone = self._listed - current
        fresh = {"never_listed": max(0, published_between(self._known, merged) - new),
                 "listed_unread": len(gone - self._read)}
        self._known, self._listed, self._read = merged, current, self._read & current
        for key, n in fresh.items():
            self.evicted_unread[key] += n
        return fresh

    def read(self, names) -> None:
        """Names the loader read (usable or not): not evicted unread, whenever they go."""
        self._read.update(names)

    @property
    def evicted_unread_total(self) -> int:
        return sum(self.evicted_unread.values())

    # ---- what the dashboard reads

    def arrivals_per_s(self) -> float | None:
        """Samples published per second (all writers), over at least MIN_WINDOW seconds
        ending at the latest listing; lists the spool when the latest is `refresh_every` old."""
        if self.clock() - self._looked >= self.refresh_every:
            self._look(self._safe_listing())
        return self.rate

    # ----

    def _safe_listing(self) -> list[str]:
        try:
            return self.list_spool(self.spool)
        except OSError:  # gone for now (the sampler says so): keep the last figures
            return self._last_names

    def _look(self, names: list[str]) -> None:
        now = self.clock()
        self._looked, self._last_names, self.count = now, names, len(names)
        highest = highest_sequences(names)
        if self._window is None:
            self._window = (now, highest)
            return
        since, before = self._window
        if now - since >= MIN_WINDOW:
            self.rate = published_between(before, highest) / (now - since)
            self._window = (now, {**before, **highest})
