"""Files that other processes read while we write them: replaced atomically, never half-written."""
from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path

from shared.spool import process_alive, remove_orphans

ORPHAN_AGE = 600.0  # s: a temporary file this old is no live writer's (a checkpoint takes seconds)


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yields a temporary path beside `path` to write; on success it replaces `path` (os.replace in
    one folder is atomic), on failure it is removed. Readers see the old file or the new one.

    The name `.tmp-<pid>-<name>` is what `sweep_orphans` parses to find a killed writer's leftovers.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json_atomically(path: Path, data, indent: int | None = None) -> None:
    """JSON to `path`, replaced atomically. NaN stays NaN: a diverged loss must show, not crash the writer."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent) + "\n")


def sweep_orphans(folder: Path, max_age: float = ORPHAN_AGE) -> int:
    """Delete `.tmp-<pid>-*` files that a killed writer left in `folder`; returns how many.

    One is an orphan when its pid is gone, or when it is older than `max_age`.
    """
    now = time.time()

    def orphan(entry: os.DirEntry) -> bool:
        try:
            pid = int(entry.name.split("-")[1])
        except (IndexError, ValueError):
            return True  # not a name we write: a stray from an older version
        return not process_alive(pid) or now - entry.stat().st_mtime > max_age

    return remove_orphans(folder, ".tmp-", orphan)


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
