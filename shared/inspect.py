"""A census of a spool: what is in it, what is corrupt, and how old it is."""
from __future__ import annotations

import os
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

from shared.sample import CorruptSample, decode_record
from shared.spool import (
    TMP_PREFIX, check_spool, enumerate_spool, foreign_names, is_sample_name, name_time, read_sample_bytes,
)


def inspect_spool(spool: Path) -> dict:
    """Decode every sample file; count samples, corrupt files, shapes, sizes, bytes and ages."""
    spool = check_spool(spool)
    entries = sorted(os.scandir(spool), key=lambda e: e.name)
    names = [e.name for e in entries if e.is_file() and is_sample_name(e.name)]
    shapes, sizes, scenes, problems = Counter(), Counter(), Counter(), Counter()
    total_bytes = corrupt = vanished = 0
    for name in names:
        try:
            data = read_sample_bytes(spool, name)
        except OSError as exc:  # unreadable (permissions, I/O error): as good as corrupt
            corrupt += 1
            problems[f"unreadable ({exc.strerror})"] += 1
            continue
        if data is None:
            vanished += 1
            continue
        total_bytes += len(data)
        try:
            record = decode_record(data)
        except ValueError as exc:  # counted by what is wrong (a field and its fault), not by each file's values
            corrupt += 1
            problems[exc.reason if isinstance(exc, CorruptSample) else str(exc).split(":")[0]] += 1
            continue
        shapes[record["shape"]] += 1
        sizes[record["size"]] += 1
        scenes[record.get("params", {}).get("scene", "?")] += 1
    samples = sum(shapes.values())
    times = [name_time(n) for n in names]
    return {
        "spool": str(spool),
        "samples": samples,
        "files": sum(1 for e in entries if e.is_file()),
        "bytes": total_bytes,
        "mean_bytes": total_bytes / max(samples + corrupt, 1),
        "corrupt": corrupt,
        "corrupt_reasons": dict(problems),
        "vanished": vanished,
        "temporary": sum(1 for e in entries if e.name.startswith(TMP_PREFIX)),
        # Hidden files (.gitkeep), the spool's own metadata, and folders named like samples
        # (which are not files, so not samples) are foreign or not as foreign_names says.
        "foreign": len(foreign_names(spool)) + sum(1 for e in entries if not e.is_file() and is_sample_name(e.name)),
        "shapes": dict(shapes),
        "size": next(iter(sizes)) if len(sizes) == 1 else sorted(sizes) or None,
        "scenes": dict(scenes),
        "oldest": _iso(min(times)) if times else None,
        "newest": _iso(max(times)) if times else None,
    }


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="milliseconds")


def freshness(spool: Path, host: str | None = None) -> dict:
    """The newest sample (of those published from `host`, a `host_tag()`, when given):
    its name, age in seconds and whether it decodes. Lists the folder and reads one
    file, so it is cheap enough for a container healthcheck on a full spool."""
    spool = check_spool(spool)
    names = enumerate_spool(spool)
    if host is not None:
        names = [n for n in names if n.split("-")[1:2] == [host]]
    for name in reversed(names):  # newest first; one evicted meanwhile gives way to the next
        data = read_sample_bytes(spool, name)
        if data is None:
            continue
        try:
            decode_record(data)
            problem = None
        except ValueError as exc:
            problem = str(exc)
        return {"spool": str(spool), "host": host, "samples": len(names), "newest": name,
                "age_s": time.time() - name_time(name), "corrupt": problem}
    return {"spool": str(spool), "host": host, "samples": 0, "newest": None, "age_s": None, "corrupt": None}
