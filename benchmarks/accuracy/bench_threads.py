"""Does `infer`'s answer depend on torch's thread count? The issue "3D you can trust", Must have 4.

Writes the first --samples noisy masks of bench_accuracy's seeded 256 px `street` and `paper`
spools (box and twobox) as PNGs, runs `cuboidtrain infer` on them with one torch thread and
with two (and, asked, with `--workers 2` and pinned to one core), and reports how many records differ and by how much (the largest corner distance).

    .venv/bin/python benchmarks/accuracy/bench_threads.py --samples 50
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import spool_for, write_masks  # noqa: E402


def infer(files: list[str], threads: int, out: Path, extra: list[str], one_core: bool = False) -> list[dict]:
    env = os.environ | {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    tool = Path(sys.executable).parent / "cuboidtrain"
    core = min(os.sched_getaffinity(0))
    subprocess.run([str(tool), "infer", *files, "--device", "cpu", "--json", str(out), *extra], env=env,
                   check=False, capture_output=True,
                   preexec_fn=(lambda: os.sched_setaffinity(0, {core})) if one_core else None)
    return json.loads(out.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=50, help="Masks a set (scene and shape).")
    parser.add_argument("--spools", type=Path, default=Path("bench-spools"))
    parser.add_argument("--workers", action="store_true", help="Also compare --workers 2 with one process.")
    parser.add_argument("--one-core", action="store_true",
                        help="Also compare a process pinned to one core (a 1-core machine: OpenCV on one thread).")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        files = []
        for scene in ("street", "paper"):
            for shape in ("box", "twobox"):
                files += write_masks(spool_for(args.spools, shape, scene, args.samples), args.samples, Path(folder))[0]
        runs = {"1 thread": infer(files, 1, Path(folder) / "one.json", []),
                "2 threads": infer(files, 2, Path(folder) / "two.json", [])}
        if args.workers:
            runs["--workers 2"] = infer(files, 1, Path(folder) / "workers.json", ["--workers", "2"])
        if args.one_core:
            runs["one core"] = infer(files, 1, Path(folder) / "one-core.json", [], one_core=True)
    base = runs["1 thread"]
    for name, records in runs.items():
        if name == "1 thread":
            continue
        moved = [float(np.abs(np.array(a["keypoints"]) - np.array(b["keypoints"])).max())
                 if a["shape"] == b["shape"] and a["keypoints"] and b["keypoints"] else float("inf")
                 for a, b in zip(base, records)]
        print(json.dumps({"against": name, "records": len(moved), "differ": sum(m > 0 for m in moved),
                          "over_0.01px": sum(m > 0.01 for m in moved), "max_px": max(moved)}))


if __name__ == "__main__":
    main()
