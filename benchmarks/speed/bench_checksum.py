"""What the samples' checksums cost (issue 39): the loader's and the generator's samples/s on one core,
with the checksum and without, interleaved and repeated in one process (medians; this machine is shared).

* the loader: one worker's part of the input path (`SpoolBatches`: read, decode, check, collate),
  over the same spool, with the payload's checksum verified (`verify=True`, what every reader does)
  and skipped (`verify=False`, which only this benchmark passes), for each --sizes spool;
* the generator: draw and encode (`make_sample` then `shared.sample.encode`, with its checksum)
  against draw and pack the same record with no checksum (format 1's single msgpack map);
* `--hashes`: instead, the microseconds a payload of each spool takes each candidate hash that
  imports here (how format 3's XXH3-64 was chosen; the others are not dependencies: install them
  beside, e.g. `pip install --target /tmp/hashes google-crc32c crc32c mmh3 blake3 cityhash`).

`--cpu-time` counts the process's CPU seconds, so that a machine busy with other work slows both
sides alike rather than whichever it preempted.

    .venv/bin/python benchmarks/speed/bench_checksum.py --repeats 9 --cpu-time --json bench-checksum.json
    PYTHONPATH=.:/tmp/hashes .venv/bin/python benchmarks/speed/bench_checksum.py --hashes --cpu-time --repeats 9
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import msgpack
import torch

from cuboidgen.config import PAPER, STREET
from cuboidgen.occluders import OccluderLibrary
from cuboidgen.synth import make_sample
from cuboidtrain.data.loader import SpoolBatches
from shared.sample import encode, to_record
from shared.spool import SpoolWriter, enumerate_spool, read_sample_bytes


def loader_rate(spool: Path, size: int, verify: bool, batch: int, clock=time.perf_counter) -> float:
    """Samples/s of one pass of `SpoolBatches` over the whole spool."""
    reader, names = SpoolBatches(spool, "box", size, verify=verify), enumerate_spool(spool)
    started = clock()
    for at in range(0, len(names), batch):
        reader[names[at : at + batch]]
    return len(names) / (clock() - started)


def generator_rate(size: int, count: int, checksum: bool, library, clock=time.perf_counter) -> float:
    """Samples/s of drawing and encoding `count` samples, with the checksum or as format 1 packed them."""
    started = clock()
    for seed in range(count):
        sample = make_sample("box", PAPER if seed % 2 else STREET, size, seed, library)
        encode(sample) if checksum else msgpack.packb(to_record(sample), use_bin_type=True)
    return count / (clock() - started)


HASHED = 64  # payloads each candidate hashes: 1.1 MB at 256 px
# Candidate hashes: (module, the call on a payload). Each is timed where its module imports.
HASHES = {
    "zlib.crc32 (format 2)": ("zlib", lambda m: m.crc32),
    "xxhash xxh3_64 (format 3)": ("xxhash", lambda m: m.xxh3_64_intdigest),
    "xxhash xxh3_128": ("xxhash", lambda m: m.xxh3_128_intdigest),
    "xxhash xxh64": ("xxhash", lambda m: m.xxh64_intdigest),
    "google-crc32c": ("google_crc32c", lambda m: m.value),
    "crc32c": ("crc32c", lambda m: m.crc32c),
    "mmh3 hash128": ("mmh3", lambda m: m.hash128),
    "farmhash 64": ("farmhash", lambda m: m.FarmHash64),
    "cityhash 64": ("cityhash", lambda m: m.CityHash64),
    "blake3": ("blake3", lambda m: lambda data: m.blake3(data).digest()),
    "hashlib blake2b-8": ("hashlib", lambda m: lambda data: m.blake2b(data, digest_size=8).digest()),
}


def hash_rows(spool: Path, size: int, repeats: int, clock=time.perf_counter) -> list[dict]:
    """Median microseconds a payload for each candidate hash that imports. The spool's first
    HASHED payloads, 20 times over a repeat: they stay in the cache, as a payload a reader has
    just read does."""
    payloads = [msgpack.unpackb(read_sample_bytes(spool, name))["payload"] for name in enumerate_spool(spool)[:HASHED]]
    calls = {}
    for name, (module, call) in HASHES.items():
        try:
            calls[name] = call(importlib.import_module(module))
        except ImportError:
            print(f"{name}: not installed, skipped")
    times = {name: [] for name in calls}
    for _ in range(repeats):  # interleaved, so every candidate sees the same machine
        for name, call in calls.items():
            started = clock()
            for payload in payloads * 20:
                call(payload)
            times[name].append((clock() - started) / (20 * len(payloads)) * 1e6)
    mean_bytes = sum(map(len, payloads)) / len(payloads)
    return sorted(({"hash": name, "px": size, "payload_bytes": round(mean_bytes), "us": round(statistics.median(t), 3)}
                   for name, t in times.items()), key=lambda row: row["us"])


def ratio_rows(measure, repeats: int) -> dict:
    """Interleaved repeats of measure(True) and measure(False): medians and their ratio."""
    on, off = [], []
    for _ in range(repeats):
        on.append(measure(True))
        off.append(measure(False))
    with_, without = statistics.median(on), statistics.median(off)
    return {"with_per_s": round(with_), "without_per_s": round(without), "ratio": round(with_ / without, 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256], help="the spools' px")
    parser.add_argument("--samples", type=int, default=1000, help="samples a spool")
    parser.add_argument("--draws", type=int, default=150, help="samples the generator draws a repeat")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--core", type=int, default=0, help="the CPU this process is pinned to")
    parser.add_argument("--cpu-time", action="store_true",
                        help="time by the process's CPU seconds, not the wall clock: on a machine shared with other work, "
                             "the time the process waited for its core is left out")
    parser.add_argument("--hashes", action="store_true", help="instead: time the candidate hashes on each spool's payloads")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    os.sched_setaffinity(0, {args.core})
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    library = OccluderLibrary.builtin(variants_per_kind=4, seed=0)
    clock, rows = time.process_time if args.cpu_time else time.perf_counter, []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            spool = Path(tmp) / f"spool-{size}"
            with SpoolWriter(spool, limit=0) as writer:
                for seed in range(args.samples):
                    writer.publish(encode(make_sample("box", PAPER if seed % 2 else STREET, size, seed, library)))
            if args.hashes:
                rows += hash_rows(spool, size, args.repeats, clock)
                continue
            loader_rate(spool, size, True, args.batch)  # warm: the page cache, first-call allocations
            rows.append({"stage": "loader", "px": size, **ratio_rows(
                lambda verify: loader_rate(spool, size, verify, args.batch, clock), args.repeats)})
            rows.append({"stage": "generator", "px": size, **ratio_rows(
                lambda checksum: generator_rate(size, args.draws, checksum, library, clock), args.repeats)})
    for row in rows:
        if args.hashes:
            print(f"{row['px']:4} px  {row['payload_bytes']:6,} B  {row['hash']:26} {row['us']:7.2f} us")
        else:
            print(f"{row['stage']:9} {row['px']:4} px  with {row['with_per_s']:7,}/s  without {row['without_per_s']:7,}/s  "
                  f"ratio {row['ratio']:.3f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
