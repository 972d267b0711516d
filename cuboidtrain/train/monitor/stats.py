"""The training run's running statistics: step rates, data wait, smoothed losses and skip counts.

The loop's events feed them (a batch fetched, a step taken, samples skipped);
the status and the metrics log read them. Nothing here writes anywhere.
"""
from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass

from cuboidtrain.data.loader import SKIP_REASONS
from cuboidtrain.train.monitor.status import BatchFreshness

WINDOW = 20  # steps: the fewest that rates and the data-wait fraction are measured over
# s: and at least this long. A GPU takes 20 steps in a second or two, and each epoch's first
# batch is waited for (the listing, the loader's queue filled afresh): over 20 steps the data
# wait swung between 0.4% and 26% on an H100 whose mean was 4-6.5% (BENCHMARKS.md, "On a GPU").
WINDOW_S = 30.0
HISTORY = 120  # loss values kept for the dashboard's trend
EMA = 0.1  # weight of the newest loss in the smoothed value
LOSSES = ("D_R", "D_S", "D_T", "total")


@dataclass(frozen=True, slots=True)
class Rates:
    """Speed over the last WINDOW steps or WINDOW_S seconds, whichever hold more; None before the first step."""

    samples_per_s: float | None = None
    step_time_s: float | None = None
    data_wait_fraction: float | None = None  # of step time


class RunningStats:
    """The figures a run keeps while it trains, updated by the loop's events."""

    def __init__(self):
        self.smoothed: dict[str, float] = {}  # exponentially smoothed losses (EMA)
        self.history = {k: deque(maxlen=HISTORY) for k in LOSSES}
        self.recent: deque[tuple[int, float, float, float]] = deque()  # (samples, waited s, step s, end) per step
        self._window = [0, 0.0, 0.0]  # samples, waited s and step s summed over `recent`
        self._summed = Counter()  # losses summed since the last metrics record
        self._summed_steps = 0
        self.skipped = Counter(dict.fromkeys(SKIP_REASONS, 0))
        self.freshness = BatchFreshness()  # the last step's
        self.foreign = 0  # files in the spool that are not samples (ignored)
        self.last_end = time.perf_counter()

    def fetched(self) -> float:
        """A batch arrived: seconds waited for it since the last step ended."""
        return time.perf_counter() - self.last_end

    def skip(self, skipped: dict) -> None:
        self.skipped.update(skipped)

    def stepped(self, losses: dict[str, float], samples: int, waited: float, age: float, reuse: float,
                skipped: dict) -> None:
        """A step was taken on `samples` samples after `waited` s of data wait."""
        now = time.perf_counter()
        self._enter((samples, waited, now - self.last_end, now))
        while len(self.recent) > WINDOW and now - self.recent[0][3] > WINDOW_S:
            self._leave(self.recent.popleft())
        self.last_end = now
        self.skipped.update(skipped)
        self.freshness = BatchFreshness(age, reuse)
        for key, value in losses.items():
            previous = self.smoothed.get(key, value)
            self.smoothed[key] = previous + EMA * (value - previous)
            self.history[key].append(value)
        self._summed.update(losses)
        self._summed_steps += 1

    def _enter(self, step: tuple[int, float, float, float]) -> None:
        self.recent.append(step)
        self._window = [total + part for total, part in zip(self._window, step[:3])]

    def _leave(self, step: tuple[int, float, float, float]) -> None:
        self._window = [total - part for total, part in zip(self._window, step[:3])]

    def window_full(self) -> bool:
        """Whether the rates cover a whole WINDOW of steps (a start-up wait is no trend)."""
        return len(self.recent) >= WINDOW

    def rates(self) -> Rates:
        """Over the last WINDOW steps, or the last WINDOW_S seconds where those hold more."""
        samples, waited, total = self._window
        return Rates(
            samples_per_s=samples / total if total else None,
            step_time_s=total / len(self.recent) if self.recent else None,
            data_wait_fraction=max(waited / total, 0.0) if total else None,  # running sums: no -0.0% from rounding
        )

    def mean_losses(self) -> dict[str, float]:
        """The mean of each loss since the last call (a metrics record's), and start summing afresh."""
        n = max(self._summed_steps, 1)
        means = {k: v / n for k, v in self._summed.items()}
        self._summed, self._summed_steps = Counter(), 0
        return means
