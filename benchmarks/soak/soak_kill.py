"""Soak: start `cuboidgen run`, SIGKILL it at a random moment, restart, many times; then
census the spool. Prints JSON: cycles, samples published, corrupt and temporary files.

    python benchmarks/soak/soak_kill.py --cycles 20 --spool /tmp/soak --limit 2000 --size 256
"""
import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from shared.inspect import inspect_spool

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--cycles", type=int, default=20)
    parser.add_argument("--spool", type=Path, default=Path("/tmp/cuboidgen-soak"))
    parser.add_argument("--limit", type=int, default=2000)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    command = [sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(args.spool), "--limit", str(args.limit),
               "--size", str(args.size), "--no-dashboard"]
    after = []
    for cycle in range(args.cycles):
        daemon = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(1.0, 4.0))
        target = rng.choice(["main", "group"])  # the main process alone, or it and its workers
        if target == "group":
            for line in subprocess.run(["pgrep", "-P", str(daemon.pid)], capture_output=True, text=True).stdout.split():
                os.kill(int(line), signal.SIGKILL)
        daemon.send_signal(signal.SIGKILL)
        daemon.wait()
        time.sleep(0.3)
        report = inspect_spool(args.spool)
        after.append({"cycle": cycle, "killed": target, "samples": report["samples"], "corrupt": report["corrupt"],
                      "temporary": report["temporary"]})
    final = subprocess.run(command[:-1] + ["--no-dashboard", "--max-samples", "1"], capture_output=True)
    report = inspect_spool(args.spool)
    print(json.dumps({
        "cycles": args.cycles, "limit": args.limit, "size": args.size,
        "corrupt_seen_after_any_kill": sum(a["corrupt"] for a in after),
        "max_temporary_after_a_kill": max(a["temporary"] for a in after),
        "after_restart": {k: report[k] for k in ("samples", "corrupt", "temporary", "foreign")},
        "per_cycle": after,
    }, indent=2))
