"""The trainer's input path on one core: read -> decode -> frame -> tensors on the device.

For each model size (64, 128, 256 px) it times, with and without reframing, two things
over the same spool, interleaved and repeated (medians: this machine is shared):

* the loader's part: `make_loader(..., workers=0)` iterated in this process, i.e. what one
  loader worker does (read, decode, frame, batch);
* the whole path: the same batches also through `prepare_batch` onto `--device` (masks
  unpacked and framed, heat maps rendered there), synchronised.

Without reframing the spool is generated at the model's size (the spool's own framing);
with reframing it is a 256 px spool, framed at the model's size as `infer` frames a mask.
The process is pinned to one core (`--core`) with torch and OpenCV on one thread, and keeps
the buffers it frees as the trainer does (`cuboidtrain.allocator`; `--glibc-default` does not).
`--equivalence SPOOL...` instead compares the reframed batches of those spools, framed on
`--device`, with the framing before issue 29 (`cuboidtrain.fit.masks`' frame of the silhouette, warp of the clean mask): the
pixels that differ and the keypoints' largest difference, at each size.

    .venv/bin/python benchmarks/speed/bench_input.py --json bench-input.json
    .venv/bin/python benchmarks/speed/bench_input.py --equivalence bench-spools/*
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import torch

from cuboidgen.config import PAPER, STREET
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.allocator import keep_freed_memory
from cuboidtrain.models.codec import default_sigma
from cuboidtrain.models.device import resolve_device
from cuboidtrain.data.loader import SpoolBatches, make_loader
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.train.startup import TRAINER_KEEPS
from shared.sample import encode
from shared.spool import SpoolWriter

SOURCE_SIZE = 256  # the reframed runs' spool: what the GPU run of issue 29 trained from


def fill(spool: Path, size: int, count: int) -> Path:
    """`count` box samples at `size` px, `paper` and `street` scenes alternating."""
    library = OccluderLibrary.builtin(variants_per_kind=4, seed=0)
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(count):
            writer.publish(encode(make_sample("box", PAPER if seed % 2 else STREET, size, seed, library)))
    return spool


def one_pass(loader, device: torch.device | None, size: int) -> tuple[int, float]:
    """(samples, seconds) for one epoch of `loader`, through `prepare_batch` on `device` unless None."""
    sigma, samples = default_sigma(size), 0
    start = time.perf_counter()
    for batch in loader:
        samples += len(batch.names)
        if device is not None and batch.names:
            prepared = prepare_batch(batch, device, sigma, size)
            if device.type == "cuda":
                torch.cuda.synchronize()
            del prepared
    return samples, time.perf_counter() - start


def bench_size(size: int, reframe: bool, spool: Path, batch: int, repeats: int, device: torch.device) -> dict:
    loader, _ = make_loader(spool, "box", size, batch, seed=0, workers=0, pin_memory=device.type == "cuda",
                            reframe="always" if reframe else "never")
    one_pass(loader, device, size)  # warm-up: page cache, allocator, kernels
    loader_rates, whole_rates = [], []
    for _ in range(repeats):  # interleaved, so both see the same machine load
        samples, seconds = one_pass(loader, None, size)
        loader_rates.append(samples / seconds)
        samples, seconds = one_pass(loader, device, size)
        whole_rates.append(samples / seconds)
    return {"size": size, "reframe": reframe, "spool_size": SOURCE_SIZE if reframe else size, "batch": batch,
            "samples_per_epoch": samples, "loader_samples_per_s": statistics.median(loader_rates),
            "whole_samples_per_s": statistics.median(whole_rates),
            "loader_runs": loader_rates, "whole_runs": whole_rates}


def equivalence(spool: Path, size: int, device: torch.device) -> dict:
    """How far the batch `prepare_batch` frames on `device` lies from the framing before issue 29."""
    from cuboidtrain.fit.masks import frame, silhouette, warp
    from shared.sample import decode_record, from_record
    from shared.spool import enumerate_spool, read_sample_bytes

    shape = "twobox" if "twobox" in spool.name else "box"
    batch = SpoolBatches(spool, shape, size, reframe="always")[enumerate_spool(spool)]
    x = prepare_batch(batch, device, default_sigma(size), size)
    x1, x2, x4 = x.x1.cpu(), x.x2.cpu(), x.x4.cpu()
    pixels, worst, keypoints = 0, 0.0, 0.0
    for row, name in enumerate(batch.names):
        sample = from_record(decode_record(read_sample_bytes(spool, name)))
        noisy, framing = frame(silhouette(sample.noisy), size)
        for prepared, mask in ((x1[row, 0], noisy), (x2[row, 0], warp(sample.clean, framing))):
            differing = int(((prepared > 0).numpy() != mask).sum())
            pixels, worst = pixels + differing, max(worst, differing / size**2)
        keypoints = max(keypoints, float(abs(x4[row].numpy() - framing.to_model(sample.keypoints)).max()))
    return {"spool": str(spool), "size": size, "device": str(device), "samples": len(batch.names), "differing_pixels": pixels,
            "worst_mask_share": worst, "keypoints_max_px": keypoints}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--batches", type=int, default=8, help="Batches per epoch (the spool holds batch x batches).")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu", help="The training device of the whole path (cpu, cuda, auto).")
    parser.add_argument("--core", type=int, default=None, help="Pin to this core (default: the last one allowed).")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--glibc-default", action="store_true",
                        help="Leave glibc's allocator as it is (the trainer keeps freed buffers: cuboidtrain.allocator).")
    parser.add_argument("--equivalence", type=Path, nargs="+", default=None, metavar="SPOOL",
                        help="Instead: compare these spools' reframed batches with the framing before issue 29.")
    args = parser.parse_args()
    if args.equivalence:
        device = resolve_device(args.device)
        rows = [equivalence(spool, size, device) for spool in args.equivalence for size in args.sizes]
        for r in rows:
            print(f"{r['spool']:36} {r['size']:4d} px  {r['samples']:4d} samples  {r['differing_pixels']:6d} px differ "
                  f"(worst mask {r['worst_mask_share']:.3%})  keypoints within {r['keypoints_max_px']:.1e} px")
        print(json.dumps(rows, indent=2))
        return
    os.sched_setaffinity(0, {args.core if args.core is not None else max(os.sched_getaffinity(0))})
    device, count, rows = resolve_device(args.device), args.batch * args.batches, []
    # on a CPU, as `cuboidtrain run` does: keep the freed buffers
    kept = not args.glibc_default and device.type == "cpu" and keep_freed_memory(TRAINER_KEEPS, TRAINER_KEEPS)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory(dir=".", prefix=".bench-input-") as tmp:
        source = fill(Path(tmp) / f"spool-{SOURCE_SIZE}", SOURCE_SIZE, count)
        for size in args.sizes:
            own = source if size == SOURCE_SIZE else fill(Path(tmp) / f"spool-{size}", size, count)
            for reframe in (False, True):
                rows.append(bench_size(size, reframe, source if reframe else own, args.batch, args.repeats, device))
                r = rows[-1]
                print(f"{size:4d} px  {'reframe   ' if reframe else 'no reframe'}  from {r['spool_size']:3d} px  "
                      f"loader {r['loader_samples_per_s']:8.0f} samples/s  whole path {r['whole_samples_per_s']:8.0f} "
                      f"samples/s", flush=True)
    result = {"device": str(device), "core": sorted(os.sched_getaffinity(0)), "torch_threads": torch.get_num_threads(),
              "freed_memory_kept": kept, "batch": args.batch, "batches": args.batches, "repeats": args.repeats, "rows": rows}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
