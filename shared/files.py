"""Files that other processes read while we write them: one atomic writer, one rule for
naming its temporary files, and one sweep that finds the ones a killed writer left.

Every temporary file, whoever writes it (a spool sample, a spool spare, a checkpoint,
status.json, SPOOL.json, a figure), is named `.tmp-0-<host>-<pid>-<name>`: the sweep
reads the writer's host and pid back from the name, so it can tell a live writer's
file from a dead one's without waiting. The first field is not read (older versions
put a time there); the host tag has no `-`, so the fields split cleanly whatever `name` holds.

Every writer goes through `atomic_path` (or `save_figure` for a picture) but one: the spool's
publish (`shared.spool.SpoolWriter`), the generator's hot path at thousands of samples a
second, names its temporary file by the same `temporary_name` with its host and pid looked
up once, creates it exclusively, may fsync it, and turns a full disk into `SpoolFull`.
"""
from __future__ import annotations

import contextlib
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
