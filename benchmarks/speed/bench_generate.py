"""Generation benchmark: published samples/s per core and bytes per sample, at 256x256.

    python benchmarks/speed/bench_generate.py [--size 256 --samples 400 --repeats 5] [--stages]
Prints a table and JSON (stdout). `--stages` adds where a sample's time goes: per-sample
medians of each stage (view, raster, occlusion, contour noise), of make_sample as a
whole, of encoding and of publishing into a spool at its cap.
"""
import argparse
import json
import os

from cuboidgen.bench import bench_daemon, bench_generate, bench_stages
from cuboidgen.occluders import OccluderLibrary

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--samples", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--stages", action="store_true", help="also time each stage of a sample")
    args = parser.parse_args()
    library = OccluderLibrary.builtin()
    result = {
        "generate": bench_generate(args.size, args.samples, args.repeats, library),
        "daemon": bench_daemon(args.size, args.samples * 4, os.cpu_count() or 1),
    }
    if args.stages:
        result["stages"] = bench_stages(args.size, args.samples, library)
    g = result["generate"]
    print(f"{'generate+encode, 1 core':36s} {g['generate_only_per_s']:>10,.0f} /s")
    print(f"{'generate+publish, 1 core':36s} {g['published_per_s_per_core']:>10,.0f} /s   target >= 2,000")
    print(f"{'daemon, all cores':36s} {result['daemon']['published_per_s']:>10,.0f} /s")
    print(f"{'bytes/sample mean (max)':36s} {g['bytes_per_sample_mean']:>10,.0f} ({g['bytes_per_sample_max']:,})   target <= 20,480")
    for key, value in result.get("stages", {}).items():
        if key.endswith("_us"):
            print(f"{'  ' + key[:-3].replace('_', ' ') + ', median':36s} {value:>10,.0f} us")
    print(json.dumps(result, indent=2))
