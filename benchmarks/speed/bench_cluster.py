"""The same masks through the local pool (`infer --workers 2`), a local Dask cluster (`infer --cluster
local --workers 2`) and Ray Data (`map_batches` with one Fitter per actor, 2 actors), in one run,
each a whole process from start to its last record stored; the records of each are checked
against the single-process run's (one torch thread), byte for byte once sorted by index.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed/bench_cluster.py --masks 400
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed/bench_cluster.py --masks 2000 --repeats 1

Ray is not a dependency of cuboid-fit: `pip install 'ray[data]'` to run its row (skipped
without it). The Ray run is this script's own (`--ray-run FOLDER OUT`): `ray.init` with
2 CPUs on 127.0.0.1, no dashboard; inputs as rows of (index, path), batches of `pool.CHUNK`
paths (`--ray-batch`), each actor reading its masks and fitting them with its Fitter at one torch thread;
the driver stores each batch's records through the same `RecordStore` as `infer --jsonl`.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from cuboidtrain.infer.pool import CHUNK  # noqa: E402  (no torch: the chunk the pool and Dask send)


class FitActor:
    """A Ray Data actor: its own Fitter, built once, one torch thread."""

    def __init__(self, checkpoints: list[str], options):
        import torch

        from cuboidtrain.fit.fitter import Fitter

        torch.set_num_threads(1)
        self.fitter = Fitter.from_files(checkpoints, options)
        self.options = self.fitter.options

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        from cuboidtrain.infer.pool import fit_one
        from cuboidtrain.infer.records import to_records

        groups = [fit_one(self.fitter, int(i), str(p)) for i, p in zip(batch["index"], batch["path"])]
        # one JSON text a input: Arrow would turn the records' dicts into structs (and `{}` into nothing)
        return {"index": np.array([i for i, _ in groups]),
                "records": np.array([json.dumps(to_records(outcomes, self.options)) for _, outcomes in groups],
                                    dtype=object)}


def ray_run(folder: str, out: str, actors: int, batch_size: int) -> None:
    """Fit every mask of `folder` with Ray Data into the JSONL store `out`; print the summary line."""
    import logging

    import ray

    from cuboidtrain.infer.inputs import gather_inputs
    from cuboidtrain.fit.options import FitOptions
    from cuboidtrain.infer.records import RecordStore
    from cuboidtrain.models.zoo import default_checkpoints

    started = time.perf_counter()
    options = FitOptions(device="cpu").validate()
    checkpoints = [str(c) for c in default_checkpoints(None, options.shapes)]
    inputs = gather_inputs([folder])
    ray.init(num_cpus=actors, include_dashboard=False, _node_ip_address="127.0.0.1", logging_level=logging.ERROR,
             log_to_driver=False, runtime_env={"env_vars": {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}})
    context = ray.data.DataContext.get_current()
    context.enable_progress_bars = False
    ready = time.perf_counter()
    rows = ray.data.from_items([{"index": i, "path": p} for i, p in enumerate(inputs)])
    fitted = rows.map_batches(FitActor, fn_constructor_args=(checkpoints, options), batch_size=batch_size,
                              compute=ray.data.ActorPoolStrategy(size=actors), num_cpus=1, batch_format="numpy")
    count = 0
    with RecordStore(out) as store:
        for batch in fitted.iter_batches(batch_size=None, batch_format="numpy"):
            for index, text in zip(batch["index"], batch["records"]):
                store.write(int(index), json.loads(text))
                count += 1
    ray.shutdown()
    end = time.perf_counter()
    print(f"ray data: {count} masks, ray.init {ready - started:.1f} s, fitting {end - ready:.1f} s "
          f"({count / (end - ready):.1f} masks/s)", flush=True)


def masks_folder(given: Path | None, tmp: Path, count: int, size: int) -> Path:
    from benchmarks.speed.bench_workers import masks_folder as folder

    return folder(given, tmp, count, size)


def timed(command: list[str]) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True,
                          env=os.environ | {"OMP_NUM_THREADS": "1"})
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    lines = (done.stdout + done.stderr).strip().splitlines()
    return seconds, next((line for line in reversed(lines) if "masks" in line), "(no summary)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--masks", type=int, default=400)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=2, help="rounds of all the runs, interleaved")
    parser.add_argument("--folder", type=Path, help="masks already written (default: generated into a temporary folder)")
    parser.add_argument("--ray-batch", type=int, default=CHUNK,
                        help=f"masks a Ray Data batch (default {CHUNK}, the pool's and Dask's chunk)")
    parser.add_argument("--ray-run", nargs=2, metavar=("FOLDER", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.ray_run:
        return ray_run(*args.ray_run, actors=2, batch_size=args.ray_batch)
    from cuboidtrain.infer.records import read_records

    try:
        import ray  # noqa: F401
        has_ray = True
    except ImportError:
        has_ray = False
    with tempfile.TemporaryDirectory() as tmp:
        folder = masks_folder(args.folder, Path(tmp), args.masks, args.size)
        infer = [sys.executable, "-m", "cuboidtrain", "infer", str(folder), "--device", "cpu", "--networks-only", "--jsonl"]
        runs = {"1 process": lambda out: infer + [out],
                "--workers 2 (pool)": lambda out: infer + [out, "--workers", "2"],
                "--cluster local --workers 2 (Dask)": lambda out: infer + [out, "--cluster", "local", "--workers", "2"]}
        if has_ray:
            runs[f"Ray Data, 2 actors, batches of {args.ray_batch}"] = lambda out: [
                sys.executable, __file__, "--ray-run", str(folder), out, "--ray-batch", str(args.ray_batch)]
        else:
            print("ray not installed: no Ray row (pip install 'ray[data]')")
        times, reference = {name: [] for name in runs}, None
        for repeat in range(args.repeats):
            for number, (name, command) in enumerate(runs.items()):
                out = Path(tmp) / f"run{repeat}-{number}.jsonl"
                load = open("/proc/loadavg").read().split()[0]
                seconds, summary = timed(command(str(out)))
                times[name].append(seconds)
                records = read_records(out)
                reference = reference or records
                same = "records identical" if records == reference else "RECORDS DIFFER"
                print(f"{name}: {seconds:.1f} s wall (load {load} before); {same}; {summary}", flush=True)
        base = statistics.median(times["1 process"])
        pool = statistics.median(times["--workers 2 (pool)"])
        for name, seconds in times.items():
            median = statistics.median(seconds)
            print(f"{name}: median {median:.1f} s of {len(seconds)}, {base / median:.2f}x one process, "
                  f"{pool / median:.2f}x the pool")


if __name__ == "__main__":
    main()
