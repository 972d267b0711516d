"""Spool read benchmark: read + decode + collate into torch tensors on one core, against
generating each sample on the fly in torch DataLoader workers (the same process).

    python benchmarks/speed/bench_spool_read.py [--size 256 --samples 2000 --batch 64 --repeats 5]
Prints a table and JSON.
"""
import argparse
import json
import os

from cuboidgen.bench import bench_on_the_fly, bench_read
from cuboidgen.occluders import OccluderLibrary

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    read = bench_read(args.size, args.samples, args.batch, args.repeats, OccluderLibrary.builtin())
    fly = bench_on_the_fly(args.size, max(args.samples // 5, 200), args.batch, os.cpu_count() or 1, 2)
    ratio = read["read_unpacked_per_s"] / fly["on_the_fly_per_s"]
    print(f"{'spool read -> tensors (unpacked), 1 core':44s} {read['read_unpacked_per_s']:>10,.0f} /s   target >= 20,000")
    print(f"{'spool read -> tensors (packed bits), 1 core':44s} {read['read_packed_per_s']:>10,.0f} /s")
    print(f"{'on the fly, DataLoader x' + str(fly['workers']):44s} {fly['on_the_fly_per_s']:>10,.0f} /s")
    print(f"{'ratio spool / on the fly':44s} {ratio:>10,.1f}x")
    print(json.dumps({"read": read, "on_the_fly": fly, "ratio_read_over_on_the_fly": ratio}, indent=2))
