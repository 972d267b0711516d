"""Files that other processes read while we write them: replaced atomically, never half-written."""
from __future__ import annotations

import json
from pathlib import Path

from shared import files
from shared.files import atomic_path

ORPHAN_AGE = 600.0  # s: a temporary file this old is no live writer's (a checkpoint takes seconds)



def sweep_orphans(folder: Path, max_age: float = ORPHAN_AGE) -> int:
    """Delete the temporary files a killed writer left in the run folder `folder`; returns how many."""
    return files.sweep_orphans(folder, max_age)


def repair_jsonl(path: Path) -> bool:
    """Cut a torn last record (a writer killed mid-line) off a JSON-lines file; True if it had one."""
    try:
        with open(path, "rb+") as f:
            data = f.read()
            if not data or data.endswith(b"\n"):
                return False
            f.truncate(data.rfind(b"\n") + 1)
            return True
    except FileNotFoundError:
        return False


def drop_records_after(path: Path, step: int) -> int:
    """Remove the records of steps after `step` (a resumed run trains them again, so they
    would appear twice); returns how many. The file is replaced atomically."""
    try:
        lines = Path(path).read_text().splitlines(keepends=True)
    except FileNotFoundError:
        return 0
    kept = [line for line in lines if _step_of(line) <= step]
    if len(kept) < len(lines):
        with atomic_path(path) as tmp:
            tmp.write_text("".join(kept))
    return len(lines) - len(kept)


def _step_of(line: str) -> float:
    try:
        return json.loads(line).get("step", 0)
    except (ValueError, AttributeError):
        return 0
