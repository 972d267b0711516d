"""`cuboidtrain infer --workers N` against one process, in the same run: N generated masks at 256 px
(box and twobox, the `paper` scene), the shipped models, one torch thread a process.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed/bench_workers.py --masks 400 --workers 1 2
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed/bench_workers.py --masks 400 --workers 1 2 --cluster 2
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed/bench_workers.py --masks 2000 --workers 1 2 --repeats 3

`--cluster N` adds `infer --cluster local --workers N` (a local Dask cluster, the `cluster` extra).
`--before DIR` adds `infer --workers N` (the largest of --workers) run from another checkout,
e.g. `git archive 7e15fd2 | tar -x -C /tmp/before` (the same venv; its own code wins on sys.path).
`--repeats R` runs the whole set R times, interleaved (1, 2, 1, 2, ...), and adds each run's
median and best; `--folder DIR` reuses masks written before (`--write-only DIR` writes them).

Times the whole command (start, models, fits, writing the JSONL, exit) and reads its fitting rate.
The fits are the networks' alone (`--networks-only`, as every figure in BENCHMARKS.md was measured
before the cuboid fit became `infer`'s default); `--cuboid` times the cuboid fit instead.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def masks_folder(given: Path | None, tmp: Path, count: int, size: int) -> Path:
    """The masks to fit: `given` (written before), else `count` new ones written under `tmp`."""
    if given is not None:
        return given
    folder = tmp / "masks"
    folder.mkdir()
    write_masks(folder, count, size)
    return folder


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
    parser.add_argument("--before", type=Path, metavar="DIR", help="also --workers N from the checkout in DIR")
    parser.add_argument("--repeats", type=int, default=1, help="rounds of all the runs, interleaved")
    parser.add_argument("--folder", type=Path, help="masks written before (default: written to a temporary folder)")
    parser.add_argument("--write-only", type=Path, metavar="DIR", help="write --masks masks to DIR and stop")
    parser.add_argument("--cuboid", action="store_true", help="time infer's cuboid fit, not the networks' alone")
    args = parser.parse_args()
    fit = [] if args.cuboid else ["--networks-only"]
    if args.write_only:
        args.write_only.mkdir(parents=True, exist_ok=True)
        return write_masks(args.write_only, args.masks, args.size)
    with tempfile.TemporaryDirectory() as tmp:
        folder = masks_folder(args.folder, Path(tmp), args.masks, args.size)
        runs = [(f"workers {w}", ["--workers", str(w), *fit], ROOT) for w in args.workers]
        if args.before:
            w = max(args.workers)
            runs.append((f"workers {w}, {args.before}", ["--workers", str(w)], args.before.resolve()))
        runs += [(f"dask local cluster {w}", ["--cluster", "local", "--workers", str(w), *fit], ROOT)
                 for w in args.cluster]
        times = {name: [] for name, _, _ in runs}
        for repeat in range(args.repeats):
            base = None
            for number, (name, extra, tree) in enumerate(runs):
                out = Path(tmp) / f"run{repeat}-{number}.jsonl"
                start = time.perf_counter()
                done = subprocess.run([sys.executable, "-m", "cuboidtrain", "infer", str(folder), "--jsonl", str(out),
                                       *extra, "--device", "cpu"], cwd=tree, capture_output=True,
                                      text=True, env=os.environ | {"OMP_NUM_THREADS": "1"})
                seconds = time.perf_counter() - start
                summary = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "(no summary)"
                base = base or seconds
                times[name].append(seconds)
                print(f"{name}: {seconds:.1f} s wall, speed-up {base / seconds:.2f}x; {summary}", flush=True)
        if args.repeats > 1:
            first = runs[0][0]
            for name, seconds in times.items():
                median, best = statistics.median(seconds), min(seconds)
                print(f"{name}: median {median:.2f} s ({statistics.median(times[first]) / median:.2f}x), "
                      f"best {best:.2f} s ({min(times[first]) / best:.2f}x) of {len(seconds)}", flush=True)


if __name__ == "__main__":
    main()
