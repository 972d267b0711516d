"""The one error for "the user gave something bad", and the check of an output path.

A `UsageError` is a bad option, file, scene file, model file, mask or spool: its message
names the value and what was expected, and both command lines print it in one line
(`shared.console.Commands`). Anything else that escapes a command is ours: a traceback.
It stays a `ValueError`, so callers that catch bad values keep catching it; nothing uses it
for control flow (a sample skipped in training, a spool tried in turn, has its own way).
"""
from __future__ import annotations

import os
from pathlib import Path


class UsageError(ValueError):
    """Something the user gave is bad; the message names it and what was expected."""


def check_writable(option: str, path: str | Path, folder: bool = False) -> Path:
    """`path` as given to `option`, if a file (or with `folder`, a folder) can be written there;
    else a UsageError naming the option. Checked before any work, so a fit or a training run
    is not lost to a typo in its output path. A file goes into a folder that exists: a missing
    one is an error, not a folder silently made (`--json /nonexistent/x.json`). A folder (a run's
    `--out`, `--explain`) may be new, with its missing parents (the writers make them): the nearest
    existing one must be a writable folder. Nothing is created here."""
    path = Path(path)
    if path.is_dir() and not folder:
        raise UsageError(f"{option} {path}: a folder, expected a file to write")
    if path.exists() and folder and not path.is_dir():
        raise UsageError(f"{option} {path}: not a folder")
    existing = path if folder and path.is_dir() else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{option} {path}: {existing} is not a folder")
    if not folder and existing != path.parent:
        raise UsageError(f"{option} {path}: no folder {path.parent} to write it in (expected an existing folder)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: cannot write in {existing} (permission denied)")
    return path


def check_outputs(*given: tuple[str, str | Path | None]) -> None:
    """`check_writable` for each (option, file) pair given; None (not asked for) and - (stdout) pass."""
    for option, path in given:
        if path is not None and str(path) != "-":
            check_writable(option, path)
