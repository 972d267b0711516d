"""One training step's time on the device by memory format: is channels-last faster here?

For each arch, size and phase it times `train_step` (bf16 autocast on CUDA, as the trainer
runs) on one real batch already on the device (a 256 px spool framed at the model's size,
`prepare_batch`), in three layouts, interleaved step by step so that all see the same load:

* `contiguous`: the model and the batch in torch's default layout (NCHW);
* `model_cl`: the model in channels-last, the batch as it comes (the trainer before issue 29's
  measurement: `startup.build_state` converted the model alone);
* `both_cl`: the model and the batch's images in channels-last.

Medians over `--repeats`; the ratio is each layout's step time over `contiguous`'s.

    .venv/bin/python benchmarks/gpu/bench_memory_format.py --device cuda --json mf.json
    .venv/bin/python benchmarks/gpu/bench_memory_format.py --device cpu --archs tiny --sizes 64 --batch 8 --repeats 3
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from cuboidgen.config import PAPER, STREET
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.models.codec import default_sigma
from cuboidtrain.models.device import resolve_device
from cuboidtrain.models.networks import build_model
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.loader import make_loader
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.train.loop import train_step
from shared.sample import encode
from shared.spool import SpoolWriter

SOURCE_SIZE = 256
LAYOUTS = ("contiguous", "model_cl", "both_cl")


def one_batch(spool: Path, size: int, batch: int, device: torch.device):
    """A reframed batch of `batch` samples from `spool`, prepared on `device` at `size` px."""
    loader, _ = make_loader(spool, "box", size, batch, seed=0, workers=0, reframe="always")
    return prepare_batch(next(iter(loader)), device, default_sigma(size), size)


def channels_last(x):
    """The batch with its image tensors (masks and heat maps) in channels-last."""
    cl = torch.channels_last
    return dataclasses.replace(x, x1=x.x1.contiguous(memory_format=cl), x2=x.x2.contiguous(memory_format=cl),
                               x3=x.x3.contiguous(memory_format=cl))


def timed(step, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def bench_one(arch: str, size: int, phase: str, batch: int, repeats: int, spool: Path,
              device: torch.device) -> dict:
    config = TrainConfig(phase=phase, size=size, arch=arch, batch_size=batch, amp=True)
    x = one_batch(spool, size, batch, device)
    base = build_model("box", size, arch=arch).to(device)
    models = {"contiguous": base, "model_cl": copy.deepcopy(base).to(memory_format=torch.channels_last),
              "both_cl": copy.deepcopy(base).to(memory_format=torch.channels_last)}  # each stepped by its own optimizer
    batches = {"contiguous": x, "model_cl": x, "both_cl": channels_last(x)}
    optimizers = {name: torch.optim.Adam(models[name].parameters(), lr=1e-6) for name in LAYOUTS}
    times = {name: [] for name in LAYOUTS}
    for round_ in range(repeats + 2):  # two warm-up rounds: cuDNN's algorithm search, the allocator
        for name in LAYOUTS:
            seconds = timed(lambda: train_step(models[name], optimizers[name], batches[name], config, device), device)
            if round_ >= 2:
                times[name].append(seconds)
    medians = {name: statistics.median(times[name]) for name in LAYOUTS}
    return {"arch": arch, "size": size, "phase": phase, "batch": batch, "device": str(device),
            **{f"{name}_ms": 1e3 * medians[name] for name in LAYOUTS},
            **{f"{name}_ratio": medians[name] / medians["contiguous"] for name in LAYOUTS[1:]}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--archs", nargs="+", default=["compact", "slim", "paper"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--phases", nargs="+", default=["1", "2"])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    device, rows = resolve_device(args.device), []
    library = OccluderLibrary.builtin(variants_per_kind=4, seed=0)
    with tempfile.TemporaryDirectory(dir=".", prefix=".bench-mf-") as tmp:
        spool = Path(tmp)
        with SpoolWriter(spool, limit=0) as writer:
            for seed in range(args.batch):
                writer.publish(encode(make_sample("box", PAPER if seed % 2 else STREET, SOURCE_SIZE, seed, library)))
        for arch in args.archs:
            for size in args.sizes:
                for phase in args.phases:
                    rows.append(r := bench_one(arch, size, phase, args.batch, args.repeats, spool, device))
                    print(f"{arch:8} {size:4d} px  phase {phase}  batch {args.batch}  contiguous {r['contiguous_ms']:7.2f} ms"
                          f"  model CL {r['model_cl_ratio']:.2f}x  model+batch CL {r['both_cl_ratio']:.2f}x", flush=True)
    result = {"device": str(device), "name": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "repeats": args.repeats, "rows": rows}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
