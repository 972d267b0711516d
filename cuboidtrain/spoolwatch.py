"""A live view of the spool for the dashboard: how many samples, how fast they arrive.

watchdog's inotify observer hears every publish (the rename of a `.tmp-` file to
its sample name) and every eviction, so the trainer knows whether its generator
keeps up without listing 10,000 names every second. The count is re-anchored
to a real listing at every epoch's start, so a missed event cannot drift far.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

from watchdog.events import FileSystemEventHandler
from watchdog.observers import Observer

from shared.spool import enumerate_spool, is_sample_name

log = logging.getLogger(__name__)


class SpoolWatcher(FileSystemEventHandler):
    def __init__(self, spool: str | Path):
        super().__init__()
        self.spool = Path(spool)
        self._lock = threading.Lock()
        self._count = len(enumerate_spool(self.spool))
        self._arrivals = 0
        self._since = time.monotonic()
        self._observer = Observer()
        try:
            self._observer.schedule(self, str(self.spool), recursive=False)
            self._observer.start()
        except OSError as exc:  # e.g. inotify watches exhausted: the count then comes from listings only
            log.warning("spool %s: cannot watch it (%s); counts refresh once per epoch", self.spool, exc)
            self._observer = None

    # watchdog callbacks, on its thread
    def on_moved(self, event) -> None:
        if is_sample_name(os.path.basename(event.dest_path)):
            self._add(1, arrived=True)

    def on_created(self, event) -> None:  # a writer that does not rename (foreign, or copied in)
        if is_sample_name(os.path.basename(event.src_path)):
            self._add(1, arrived=True)

    def on_deleted(self, event) -> None:
        if is_sample_name(os.path.basename(event.src_path)):
            self._add(-1)

    def _add(self, delta: int, arrived: bool = False) -> None:
        with self._lock:
            self._count = max(0, self._count + delta)
            self._arrivals += arrived

    @property
    def count(self) -> int:
        return self._count

    def anchor(self, count: int) -> None:
        """Set the count from a real listing (the sampler lists the spool every epoch)."""
        with self._lock:
            self._count = count

    def arrivals_per_s(self) -> float:
        """Samples published per second since the last call."""
        with self._lock:
            now = time.monotonic()
            rate = self._arrivals / max(now - self._since, 1e-9)
            self._arrivals, self._since = 0, now
        return rate

    def stop(self) -> None:
        if self._observer is not None:
            self._observer.stop()
            self._observer.join(timeout=5)

    def __enter__(self) -> "SpoolWatcher":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
