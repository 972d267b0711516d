"""Soak: a generator and a trainer on one rotating spool, SIGKILLed at random moments, many times.

Each cycle waits a random time, then SIGKILLs the trainer, the generator or both (the
whole process group: loader and generation workers too), checks what they left, and
restarts them (the trainer with --resume once it has a checkpoint). Meanwhile a watcher
lists the spool every 0.1 s. Prints JSON:

* torn: corrupt samples found by a census of the spool after every kill, plus corrupt
  samples the trainer skipped (it decodes every sample it reads); must be 0;
* lost published: samples that vanished while an older one was still there (eviction
  is oldest first, and one generator worker keeps that order strict); must be 0;
* checkpoints: last.pt loads after every kill, and its step never goes backwards;
* temporary files left in the run folder by a kill, and whether the next start swept them;
* resumes: restarts that trained past their checkpoint before the next kill, and a final
  --resume run that must finish, with metrics.jsonl holding each step once, in order.

    nice -n 10 .venv/bin/python benchmarks/soak/soak_faults.py --cycles 15 --workdir /tmp/cuboid-soak
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from cuboidtrain.models.checkpoint import load_checkpoint
from shared.inspect import inspect_spool
from shared.spool import enumerate_spool

ROOT = Path(__file__).resolve().parents[2]


class SpoolWatch(threading.Thread):
    """Lists the spool every `every` s: what was published, and whether anything vanished out of age order."""

    def __init__(self, spool: Path, every: float = 0.1):
        super().__init__(daemon=True)
        self.spool, self.every = spool, every
        self.last_seq: dict[str, int] = {}  # writer (host-pid-token) -> highest sequence number seen
        self.lost: list[str] = []
        self.halt = threading.Event()

    def run(self) -> None:
        previous: set[str] = set()
        while not self.halt.is_set():
            try:
                names = enumerate_spool(self.spool)
            except FileNotFoundError:
                names = []
            current = set(names)
            for name in current - previous:
                writer, seq = name[: name.rindex("-")].split("-", 1)[1], int(name.rsplit("-", 1)[1].split(".")[0])
                self.last_seq[writer] = max(self.last_seq.get(writer, 0), seq)
            self._check_order(previous - current, names)
            previous = current
            time.sleep(self.every)

    def _check_order(self, vanished: set[str], names: list[str]) -> None:
        # A listing races deletions, so confirm with the file itself: an older sample that
        # exists *now*, after the younger one was deleted, was passed over by eviction.
        for name in vanished:
            older = [n for n in names[:3] if n < name]
            if any(os.path.exists(self.spool / n) for n in older):
                self.lost.append(name)

    def published(self) -> int:
        return sum(self.last_seq.values())


def start(command: list[str], log: Path) -> subprocess.Popen:
    with open(log, "a") as f:
        return subprocess.Popen(command, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})


def kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def status_of(run: Path) -> dict:
    try:
        return json.loads((run / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def _logged_steps(run: Path) -> list[int]:
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [r["step"] for r in records if "D_R" in r]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=15)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/cuboid-soak"))
    parser.add_argument("--limit", type=int, default=300)
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--checkpoint-every", type=int, default=3)
    parser.add_argument("--delay", type=float, nargs=2, default=(2.0, 9.0), help="kill after this many s (uniform)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    shutil.rmtree(args.workdir, ignore_errors=True)
    spool, run, logs = args.workdir / "spool", args.workdir / "run", args.workdir / "logs"
    logs.mkdir(parents=True)
    gen_cmd = [sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(spool), "--limit", str(args.limit),
               "--size", str(args.size), "--workers", "1", "--no-dashboard"]
    train_cmd = [sys.executable, "-m", "cuboidtrain", "run", "--spool", str(spool), "--size", str(args.size),
                 "--batch-size", str(args.batch_size), "--threads", "1", "--loader-workers", "1", "--out", str(run),
                 "--checkpoint-every", str(args.checkpoint_every), "--log-every", "1", "--no-dashboard"]
    resume = lambda: ["--resume"] if (run / "last.pt").exists() else []  # noqa: E731

    generator = start(gen_cmd, logs / "generator.log")
    while not spool.is_dir() or len(enumerate_spool(spool)) < args.batch_size:
        time.sleep(0.1)
    watch = SpoolWatch(spool)
    watch.start()
    trainer = start(train_cmd, logs / "trainer.log")
    cycles, ckpt_steps, torn_read, trained = [], [0], 0, 0
    started_at = time.time()
    for cycle in range(args.cycles):
        time.sleep(rng.uniform(*args.delay))
        victim = rng.choice(["trainer", "generator", "both"])
        before = status_of(run)
        if victim in ("trainer", "both"):
            kill_group(trainer)
        if victim in ("generator", "both"):
            kill_group(generator)
        time.sleep(0.3)
        record = {"cycle": cycle, "killed": victim, "spool_corrupt": inspect_spool(spool)["corrupt"]}
        if victim in ("trainer", "both"):
            ours = before.get("pid") == trainer.pid  # the killed trainer had started and reported
            record["trainer_step_at_kill"] = before.get("step") if ours else None
            record["resumed_and_trained"] = bool(ours and before.get("step", 0) > ckpt_steps[-1])
            torn_read += (before.get("skipped") or {}).get("corrupt", 0) if ours else 0
            trained += max(0, before.get("step", 0) - ckpt_steps[-1]) if ours else 0
            try:
                step = load_checkpoint(run / "last.pt")["step"] if (run / "last.pt").exists() else 0
                record["checkpoint"] = step
            except ValueError as exc:
                record["checkpoint"], step = f"unreadable: {exc}", -1
            record["step_went_back"] = step < ckpt_steps[-1]
            ckpt_steps.append(step)
            leftovers = sorted(p.name for p in run.glob(".tmp-*"))
            record["temp_files_left"] = len(leftovers)
            trainer = start(train_cmd + resume(), logs / "trainer.log")
            deadline = time.monotonic() + 120
            while status_of(run).get("pid") != trainer.pid and time.monotonic() < deadline:
                time.sleep(0.2)
            record["temp_files_swept_on_restart"] = not any((run / name).exists() for name in leftovers)
        if victim in ("generator", "both"):
            generator = start(gen_cmd, logs / "generator.log")
        cycles.append(record)
        print(json.dumps(record), flush=True)

    # The end: the trainer finishes a --resume run a few steps past its checkpoint, the generator stops cleanly.
    kill_group(trainer)
    final_from = load_checkpoint(run / "last.pt")["step"] if (run / "last.pt").exists() else 0
    final = subprocess.run(train_cmd + resume() + ["--steps", str(final_from + 4)], cwd=ROOT, capture_output=True,
                           text=True, env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})
    final_status = status_of(run)
    torn_read += (final_status.get("skipped") or {}).get("corrupt", 0)
    generator.send_signal(signal.SIGTERM)
    generator.wait(timeout=60)
    time.sleep(0.5)
    watch.halt.set()
    watch.join()
    census = inspect_spool(spool)
    trainer_kills = [c for c in cycles if "checkpoint" in c]
    print(json.dumps({
        "cycles": args.cycles, "seconds": round(time.time() - started_at), "limit": args.limit, "size": args.size,
        "kills": {"trainer": sum(c["killed"] == "trainer" for c in cycles),
                  "generator": sum(c["killed"] == "generator" for c in cycles),
                  "both": sum(c["killed"] == "both" for c in cycles)},
        "samples_published_at_least": watch.published(),
        "samples_trained_on_at_least": (trained + final_status.get("step", 0) - final_from) * args.batch_size,
        "torn": sum(c["spool_corrupt"] for c in cycles) + census["corrupt"] + torn_read,
        "lost_published": len(watch.lost),
        "checkpoint_unreadable": sum(isinstance(c["checkpoint"], str) for c in trainer_kills),
        "checkpoint_step_went_back": sum(c["step_went_back"] for c in trainer_kills),
        "checkpoint_steps": ckpt_steps[1:],
        "trainer_restarts": len(trainer_kills),
        "restarts_that_trained_past_their_checkpoint": sum(c["resumed_and_trained"] for c in trainer_kills),
        "temp_files_left_by_kills": sum(c["temp_files_left"] for c in trainer_kills),
        "temp_files_not_swept_by_restart": sum(not c["temp_files_swept_on_restart"] for c in trainer_kills),
        "final_resume": {"exit": final.returncode, "from_step": final_from, "state": final_status.get("state"),
                         "step": final_status.get("step")},
        "final_census": {k: census[k] for k in ("samples", "corrupt", "temporary", "foreign")},
        "run_folder_temp_files_at_end": len(list(run.glob(".tmp-*"))),
        "metrics_steps_once_each_in_order": _logged_steps(run) == list(range(1, final_status.get("step", 0) + 1)),
    }, indent=2))


if __name__ == "__main__":
    main()
