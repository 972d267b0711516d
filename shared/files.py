"""Files that other processes read while we write them: one atomic writer, one rule for
naming its temporary files, and one sweep that finds the ones a killed writer left.

Every temporary file, whoever writes it (a spool sample, a spool spare, a checkpoint,
status.json, SPOOL.json, a figure), is named `.tmp-0-<host>-<pid>-<name>`: the sweep
reads the writer's host and pid back from the name, so it can tell a live writer's
file from a dead one's without waiting. The first field is not read (older versions
put a time there); the host tag has no `-`, so the fields split cleanly whatever `name` holds.

Every JSON the project writes, to a file or to stdout, is made by `json_text` (files: `write_json`):
strict JSON, so a NaN or an Infinity is an error naming where it lies, never a bare `NaN` token
that strict parsers reject.

Every writer goes through `atomic_path` (or `save_figure` for a picture) but one: the spool's
publish (`shared.spool.SpoolWriter`), the generator's hot path at thousands of samples a
second, names its temporary file by the same `temporary_name` with its host and pid looked
up once, creates it exclusively, may fsync it, and turns a full disk into `SpoolFull`.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import socket
import time
from pathlib import Path

TMP_PREFIX = ".tmp-"


def host_tag() -> str:
    """This host's name, letters and digits only (it is a field of file names split on `-`)."""
    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:24] or "host"


def process_alive(pid: int | None) -> bool:
    """Whether `pid` runs on this host. A zombie is dead: a killed daemon's workers stay
    zombies for as long as an init without reaping (a container's PID 1) leaves them."""
    if not isinstance(pid, int) or pid <= 0:  # os.kill(0 or -n) would signal a process group
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, owned by someone else
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):  # no /proc here: kill(0) said it exists
        return True


def temporary_name(name: str, host: str | None = None, pid: int | None = None) -> str:
    """The name under which this process (or `host`, `pid`) writes `name` before renaming it."""
    host = host_tag() if host is None else host
    pid = os.getpid() if pid is None else pid
    return f"{TMP_PREFIX}0-{host}-{pid}-{name}"


def temporary_writer(name: str) -> tuple[str, int] | None:
    """The (host, pid) that wrote temporary file `name`; None when it is not a name we write."""
    if not name.startswith(TMP_PREFIX):
        return None
    parts = name[len(TMP_PREFIX):].split("-", 3)
    if len(parts) < 4 or not parts[1] or not (parts[2].isascii() and parts[2].isdigit()):
        return None
    return parts[1], int(parts[2])


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yields a temporary path beside `path` to write; on success it replaces `path` (os.replace in
    one folder is atomic), on failure it is removed. Readers see the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(temporary_name(path.name))
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def json_text(data, indent: int | None = None, what: str = "JSON", default=None) -> str:
    """`data` as strict JSON text: a NaN or an Infinity anywhere in it raises a one-line ValueError
    naming `what` and where the value lies (`records[2].keypoints[3][0] is nan`)."""
    try:
        return json.dumps(data, indent=indent, allow_nan=False, default=default)
    except ValueError:
        found = non_finite(data)
        if found is None:
            raise
        raise ValueError(f"{what}: {found[0]} is {found[1]}, which JSON cannot hold; nothing was written") from None


def non_finite(data, where: str = "") -> tuple[str, float] | None:
    """The first NaN or Infinity in nested dicts, lists and tuples: (its path, the value), or None."""
    if isinstance(data, float):
        return None if math.isfinite(data) else (where or "the value", data)
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, (list, tuple)) else ()
    for key, value in items:
        found = non_finite(value, f"{where}[{key}]" if isinstance(key, int) else f"{where}.{key}" if where else str(key))
        if found is not None:
            return found
    return None


def write_json(path: str | Path, data, indent: int | None = None, default=None) -> None:
    """`json_text(data)` to `path`, replaced atomically; checked before the temporary file is made."""
    text = json_text(data, indent, str(path), default)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def save_figure(fig, path: str | Path, dpi: int) -> Path:
    """A matplotlib figure as a picture (its format from the suffix), replaced atomically, then closed."""
    import matplotlib.pyplot as plt  # only the writers of figures pay for matplotlib

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)
    return Path(path)


def sweep_orphans(folder: str | Path, max_age: float) -> int:
    """Delete the temporary files that killed writers left in `folder`; returns how many.

    One is an orphan when its writer ran on this host and is gone, or when it is older
    than `max_age` seconds (a writer on another host cannot be asked). A `.tmp-` file
    not named by `temporary_name` is a stray (an older version's) and goes at once.
    One that vanishes meanwhile (its writer renamed or removed it) is skipped.
    """
    here, now, swept = host_tag(), time.time(), 0
    for entry in os.scandir(folder):
        if not entry.name.startswith(TMP_PREFIX):
            continue
        try:
            if _orphan(entry, here, now, max_age):
                os.unlink(entry.path)
                swept += 1
        except FileNotFoundError:
            continue
    return swept


def _orphan(entry: os.DirEntry, here: str, now: float, max_age: float) -> bool:
    writer = temporary_writer(entry.name)
    if writer is None:
        return True
    host, pid = writer
    return (host == here and not process_alive(pid)) or now - entry.stat().st_mtime > max_age
