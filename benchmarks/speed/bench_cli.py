"""A user's first `cuboidtrain infer MASK`: the whole command's wall time, start-up included.

A one-mask `infer` is mostly start-up: Python, torch, the project's modules, the two
shipped models, then one fit. Each repeat runs, interleaved so that both see the same load:

* baseline: `python -c "import torch"` (the floor no change to this project can lower);
* infer: `cuboidtrain infer examples/building.png --json -` (stdout to a pipe, discarded);
* infer --explain: the same with its Figure 4 panel (matplotlib comes in).

Medians over --repeats; `over torch` is the median of each repeat's ratio to the baseline,
so a busy machine moves both. It also lists the modules a plain infer imported that a fit
with the shipped models does not need (tests/test_layout.py holds that list empty).

    .venv/bin/python benchmarks/speed/bench_cli.py --repeats 7 --json bench-cli.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
MASK = ROOT / "examples" / "building.png"
WATCHED = ("torchvision", "torch._dynamo", "matplotlib", "onnxruntime", "cuboidgen")


def timed(command: list[str]) -> float:
    began = time.perf_counter()
    subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - began


def imported_by_infer() -> list[str]:
    """Which WATCHED modules `cuboidtrain infer` (one mask, no picture) has loaded when it ends."""
    code = ("import atexit, json, sys\n"
            f"atexit.register(lambda: print('MODULES', json.dumps(sorted(m for m in {WATCHED!r} if m in sys.modules)), "
            "file=sys.stderr))\n"
            "from cuboidtrain.cli import app\n"
            f"sys.argv = ['cuboidtrain', 'infer', {str(MASK)!r}, '--json', '-']\n"
            "app()\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    line = next(line for line in done.stderr.splitlines() if line.startswith("MODULES"))
    return json.loads(line.removeprefix("MODULES "))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.repeats < 1:
        raise SystemExit(f"--repeats {args.repeats}: expected a positive number")
    with tempfile.TemporaryDirectory() as explain:
        commands = {
            "import torch (baseline)": [sys.executable, "-c", "import torch"],
            "infer": [str(BIN / "cuboidtrain"), "infer", str(MASK), "--json", "-"],
            "infer --explain": [str(BIN / "cuboidtrain"), "infer", str(MASK), "--json", "-", "--explain", explain],
        }
        timed(commands["infer"])  # warm the page cache: every repeat then reads the same files from memory
        times = {name: [] for name in commands}
        for _ in range(args.repeats):
            for name, command in commands.items():
                times[name].append(timed(command))
    baseline = times["import torch (baseline)"]
    rows = [{"command": name, "median_s": statistics.median(t), "min_s": min(t),
             "over_torch": statistics.median(a / b for a, b in zip(t, baseline))} for name, t in times.items()]
    print(f"{'command':26s} {'median s':>9s} {'min s':>7s} {'over torch':>10s}")
    for r in rows:
        print(f"{r['command']:26s} {r['median_s']:9.2f} {r['min_s']:7.2f} {r['over_torch']:10.2f}")
    modules = imported_by_infer()
    print(f"modules a plain infer loaded of {', '.join(WATCHED)}: {', '.join(modules) or 'none'}")
    result = {"repeats": args.repeats, "rows": rows, "times_s": times, "infer_imported": modules}
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
