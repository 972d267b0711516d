"""The training run's metrics log: one line per record in OUT/metrics.jsonl, the same figures in TensorBoard.

Only the writing rank (rank 0 under torchrun) writes; TensorBoard is optional.
"""
from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

from cuboidtrain.train.monitor.stats import Rates
from cuboidtrain.train.monitor.status import BatchFreshness, Validation
from shared.files import json_text

METRICS_FILE = "metrics.jsonl"
# metrics.jsonl keys shown in TensorBoard; the losses under their own names, the rates under speed/
SCALARS = ("D_R", "D_S", "D_T", "total", "samples_per_s", "data_wait_fraction")


def tensorboard_writer(out: Path):
    """A SummaryWriter when tensorboard is installed, else None (it is optional)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tensorboard"))


class MetricsLog:
    """Appends the run's records to metrics.jsonl and TensorBoard; `writes` False: writes nothing."""

    def __init__(self, out: Path, writes: bool = True):
        self.path, self.writes = Path(out) / METRICS_FILE, writes
        self.tensorboard = tensorboard_writer(Path(out)) if writes else None

    def record(self, step: int, epoch: int, losses: dict[str, float], rates: Rates, freshness: BatchFreshness,
               skipped: dict[str, int]) -> None:
        """The training figures at `step`: `losses` averaged since the last record."""
        record = {"step": step, "epoch": epoch, "time": time.time(), **losses, **asdict(rates),
                  **asdict(freshness), "skipped": skipped}
        self._append(record)
        if self.tensorboard is not None:
            for key in SCALARS:
                if record.get(key) is not None:
                    self.tensorboard.add_scalar(key if key.startswith("D_") or key == "total" else f"speed/{key}",
                                                record[key], step)

    def validated(self, val: Validation) -> None:
        self._append({"step": val.step, "time": time.time(), "val": asdict(val)})
        if self.tensorboard is not None:
            self.tensorboard.add_scalar("val/mean_px_error", val.mean_px_error, val.step)

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()

    def _append(self, record: dict) -> None:
        if not self.writes:
            return
        with open(self.path, "a") as f:
            f.write(json_text(record, what=str(self.path)) + "\n")
