"""How fresh a batch is: its samples' age (from their names' publish time) and how often each was used before."""
from __future__ import annotations

import time

import numpy as np

from shared.spool import name_time


class FreshnessMeter:
    """Measures how fresh each batch trained on is (its samples' age, how often each was used
    before) from a use count per sample name (the status shows the reading: status.BatchFreshness)."""

    def __init__(self):
        self.uses: dict[str, int] = {}

    def observe(self, names: list[str], now: float | None = None) -> tuple[float, float]:
        """Counts one more use of each name; returns (mean age s, mean earlier uses) of the batch."""
        now = time.time() if now is None else now
        if not names:
            return 0.0, 0.0
        ages = [now - name_time(n) for n in names]
        earlier = [self.uses.get(n, 0) for n in names]
        for n in names:
            self.uses[n] = self.uses.get(n, 0) + 1
        return float(np.mean(ages)), float(np.mean(earlier))

    def forget_except(self, names: list[str]) -> None:
        """Drop counts of evicted samples so memory stays bounded by the spool."""
        live = set(names)
        self.uses = {n: c for n, c in self.uses.items() if n in live}
