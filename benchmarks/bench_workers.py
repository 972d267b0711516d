"""`cuboidtrain infer --workers N` against one process, in the same run: N generated masks at 256 px
(box and twobox, the `paper` scene), the shipped models, one torch thread a process.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_workers.py --masks 400 --workers 1 2
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_workers.py --masks 400 --workers 1 2 --cluster 2

`--cluster N` adds `infer --cluster local --workers N` (a local Dask cluster, the `cluster` extra).

Times the whole command (start, models, fits, writing the JSONL) and reads its fitting rate.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def write_masks(folder: Path, count: int, size: int) -> None:
    from cuboidgen.config import PAPER
    from cuboidgen.occluders import OccluderLibrary
    from cuboidgen.synth import make_sample

    library = OccluderLibrary.builtin(variants_per_kind=2, seed=0)
    for seed in range(count):
        sample = make_sample("mix", PAPER, size, seed, library)
        cv2.imwrite(str(folder / f"m{seed:05d}.png"), sample.noisy.astype("uint8") * 255)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--masks", type=int, default=400)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cluster", type=int, nargs="*", default=[], metavar="N",
                        help="also a local Dask cluster of N worker processes")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "masks"
        folder.mkdir()
        write_masks(folder, args.masks, args.size)
        base = None
        runs = [(f"workers {w}", ["--workers", str(w)]) for w in args.workers]
        runs += [(f"dask local cluster {w}", ["--cluster", "local", "--workers", str(w)]) for w in args.cluster]
        for number, (name, extra) in enumerate(runs):
            out = Path(tmp) / f"run{number}.jsonl"
            start = time.perf_counter()
            done = subprocess.run([sys.executable, "-m", "cuboidtrain", "infer", str(folder), "--jsonl", str(out),
                                   *extra, "--device", "cpu"], cwd=ROOT, capture_output=True,
                                  text=True, env=os.environ | {"OMP_NUM_THREADS": "1"})
            seconds = time.perf_counter() - start
            summary = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "(no summary)"
            base = base or seconds
            print(f"{name}: {seconds:.1f} s wall, speed-up {base / seconds:.2f}x; {summary}", flush=True)


if __name__ == "__main__":
    main()
