"""Files that other processes read while we write them: replaced atomically, never half-written."""
from __future__ import annotations

import json
import os
from pathlib import Path


def write_json_atomically(path: Path, data, indent: int | None = None) -> None:
    """JSON to a temporary file in the same folder (so os.replace stays atomic), then renamed over `path`.

    NaN stays NaN: a diverged loss must show, not crash the writer.
    """
    path = Path(path)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        tmp.write_text(json.dumps(data, indent=indent) + "\n")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
