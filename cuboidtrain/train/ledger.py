"""Which bytes each step trained on: OUT/ledger.jsonl, one line a step (`--ledger`).

A line is {"step": N, "rank": R, "samples": [[name, checksum], ...]}: each sample of the step's batch
on this rank by its spool name and its payload's checksum as read (and checked: `shared.sample`). An
audit (benchmarks/soak/soak_faults.py) compares them with the files a saboteur damaged: a sample
read after its damage would carry another checksum than the one written. Lines are appended and
flushed, not synced: a killed trainer may leave a torn last line, which start-up cuts
(`run_files.repair_jsonl`); the steps after a resumed checkpoint are trained, and so listed, again.
"""
from __future__ import annotations

import json
from pathlib import Path
from shared.files import json_text

LEDGER = "ledger.jsonl"


class Ledger:
    """Appends each step's samples to `path` (every rank to its own file under torchrun)."""

    def __init__(self, path: Path, rank: int = 0):
        self.path, self.rank = path, rank
        self._file = open(path, "a", encoding="utf-8")

    @classmethod
    def in_folder(cls, out: Path, rank: int = 0) -> "Ledger":
        return cls(out / (LEDGER if rank == 0 else f"ledger-rank{rank}.jsonl"), rank)

    def record(self, step: int, names: list[str], checksums: list[int]) -> None:
        line = {"step": step, "rank": self.rank, "samples": [[n, c] for n, c in zip(names, checksums)]}
        self._file.write(json_text(line) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_ledger(path: Path) -> list[dict]:
    """The ledger's whole lines (a torn last line, from a kill, left out)."""
    lines = []
    for text in path.read_text(encoding="utf-8").splitlines():
        try:
            lines.append(json.loads(text))
        except ValueError:
            continue
    return lines
