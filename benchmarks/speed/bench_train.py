"""Training throughput per phase and size, and how much of a step is spent waiting for data.

For each size and phase it times steps fed by the real spool loader (DataLoader
workers reading a spool on disk) and, in the same process as a baseline, the
same steps on a batch already in memory. Their ratio is the loader's cost;
the data-wait fraction is time blocked on the loader over total step time.

    .venv/bin/python benchmarks/speed/bench_train.py --sizes 64 128 256 --json bench-train.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from cuboidgen.occluders import OccluderLibrary
from cuboidgen.config import PAPER
from cuboidgen.synth import make_sample
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.loader import make_loader
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.models.networks import build_model
from cuboidtrain.models.device import resolve_device
from cuboidtrain.train.loop import train_step
from shared.sample import encode
from shared.spool import SpoolWriter


def fill(spool: Path, shape: str, size: int, count: int) -> None:
    library = OccluderLibrary.builtin(variants_per_kind=4, seed=0)
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(count):
            writer.publish(encode(make_sample(shape, PAPER, size, seed, library)))


def time_steps(model, optimizer, config, device, batches) -> tuple[float, float]:
    """(seconds per step, fraction of it spent waiting) over the given batch iterator."""
    waited = total = 0.0
    steps = 0
    end = time.perf_counter()
    for batch in batches:
        fetched = time.perf_counter()
        train_step(model, optimizer, prepare_batch(batch, device, config.heatmap_sigma, config.size), config, device)
        if device.type == "cuda":
            torch.cuda.synchronize()
        now = time.perf_counter()
        waited, total, steps = waited + fetched - end, total + now - end, steps + 1
        end = now
    return total / steps, waited / total


def bench_one(shape: str, size: int, phase: str, batch: int, steps: int, repeats: int, workers: int,
              spool: Path, device: torch.device) -> dict:
    config = TrainConfig(phase=phase, shape=shape, size=size, batch_size=batch, steps=steps, spool=str(spool))
    model = build_model(shape, size).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    loader, sampler = make_loader(spool, shape, size, batch, seed=0, workers=workers, pin_memory=device.type == "cuda")
    fed, waits, baseline = [], [], []
    first = next(iter(loader))
    time_steps(model, optimizer, config, device, [first])  # warm-up: allocator, kernels
    for _ in range(repeats):
        iterator = iter(loader)
        per_step, wait = time_steps(model, optimizer, config, device, (next(iterator) for _ in range(steps)))
        fed.append(per_step)
        waits.append(wait)
        baseline.append(time_steps(model, optimizer, config, device, [first] * steps)[0])
    per_step, in_memory = statistics.median(fed), statistics.median(baseline)
    return {
        "shape": shape, "size": size, "phase": phase, "batch": batch, "device": str(device),
        "samples_per_s": batch / per_step, "in_memory_samples_per_s": batch / in_memory,
        "loader_vs_in_memory": in_memory / per_step, "data_wait_fraction": statistics.median(waits),
        "step_s": per_step,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--phases", nargs="+", default=["1", "2"])
    parser.add_argument("--shape", default="box")
    parser.add_argument("--batch", type=int, default=None, help="Default: 16 at 64 px, 8 at 128, 4 at 256.")
    parser.add_argument("--steps", type=int, default=4, help="Steps per repeat.")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=1, help="DataLoader workers.")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: all cores).")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for size in args.sizes:
        batch = args.batch or {64: 16, 128: 8}.get(size, 4)
        with tempfile.TemporaryDirectory(dir=".") as tmp:
            fill(Path(tmp), args.shape, size, batch * (args.steps + 1) * 2)
            for phase in args.phases:
                rows.append(bench_one(args.shape, size, phase, batch, args.steps, args.repeats, args.workers,
                                      Path(tmp), device))
                r = rows[-1]
                print(f"{r['shape']:6} {size:4d} px  phase {phase:3}  batch {batch:3d}  {r['samples_per_s']:8.1f} samples/s"
                      f"  in memory {r['in_memory_samples_per_s']:8.1f}  ratio {r['loader_vs_in_memory']:.2f}"
                      f"  data wait {r['data_wait_fraction']:.1%}", flush=True)
    result = {"device": str(device), "torch_threads": torch.get_num_threads(), "steps": args.steps,
              "repeats": args.repeats, "loader_workers": args.workers, "rows": rows}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
