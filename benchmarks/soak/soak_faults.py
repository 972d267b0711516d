"""Soak: a generator and a trainer on one rotating spool, SIGKILLed at random moments, many times,
while a saboteur damages published samples and the spool's disk is held full for part of the run.

Each cycle waits a random time (mostly short, so kills land in start-up, mid-step and mid-publish;
now and then long, so the trainer trains past its checkpoint), then SIGKILLs the trainer, the
generator or both (the whole process group: loader and generation workers too), checks what they
left, and restarts them (the trainer with --resume once it has a checkpoint). Meanwhile:

* a watcher lists the spool every 0.1 s (a sample vanishing while an older one is still there
  was lost: eviction is oldest first);
* a saboteur damages a published sample every --sabotage-every s: flips 1-3 bits in place,
  truncates it, or replaces it with foreign bytes, and notes the checksum it was written with;
* the spool is a tmpfs of --tmpfs-mb (the run makes it; root), and for --full-share of the
  cycles a ballast file holds it full: the generator's writes fail with ENOSPC and back off.

The trainer runs with --ledger, so every step's samples are listed by name and payload checksum:
a damaged sample trained on would show as a damaged name with a checksum other than the one written.
Prints a JSON line per cycle, then the report (RELIABILITY.md gives the last one's table):

    nice -n 10 .venv/bin/python benchmarks/soak/soak_faults.py --cycles 1000 --workdir /tmp/cuboid-soak
"""
from __future__ import annotations

import argparse
import errno
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import msgpack

from cuboidtrain.models.checkpoint import DamagedFile, load_checkpoint
from cuboidtrain.train.ledger import read_ledger
from shared.sample import decode_record
from shared.spool import enumerate_spool

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("flip", "truncate", "foreign")


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


class Saboteur(threading.Thread):
    """Damages a random published sample every `every` s and checks that the readers' decoder
    refuses it. `damaged`: name -> (kind, the checksum it was written with)."""

    def __init__(self, spool: Path, every: float, rng: random.Random):
        super().__init__(daemon=True)
        self.spool, self.every, self.rng = spool, every, rng
        self.damaged: dict[str, tuple[str, int]] = {}
        self.refused: Counter = Counter()  # kind -> damaged files the decoder refused
        self.accepted: list[str] = []  # damaged files the decoder took: must stay empty
        self.no_space = 0  # foreign replacements the full disk refused
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.wait(self.every):
            names = [n for n in enumerate_spool(self.spool) if n not in self.damaged]
            if names:
                self.damage(self.rng.choice(names), self.rng.choice(KINDS))

    def damage(self, name: str, kind: str) -> None:
        path = self.spool / name
        try:
            data = path.read_bytes()
            written = msgpack.unpackb(data)["checksum"]
            if kind == "flip":
                with open(path, "r+b") as f:
                    for bit in self.rng.sample(range(len(data) * 8), self.rng.randint(1, 3)):
                        f.seek(bit // 8)
                        byte = f.read(1)[0] ^ (0x80 >> bit % 8)
                        f.seek(bit // 8)  # the read moved on: write the flipped byte where it was read
                        f.write(bytes([byte]))
            elif kind == "truncate":
                os.truncate(path, self.rng.randrange(len(data)))
            else:  # foreign bytes under the sample's name, as a bad copy would leave them
                tmp = path.with_name(f".sabotage-{name}")
                tmp.write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(self.rng.randint(8, len(data))))
                os.replace(tmp, path)
            damaged = path.read_bytes()
        except FileNotFoundError:  # evicted meanwhile
            return
        except OSError as exc:
            if exc.errno != errno.ENOSPC:
                raise
            self.no_space += 1
            return
        if damaged == data:  # the writer recycled the file meanwhile: not damaged after all
            return
        self.damaged[name] = (kind, written)
        try:
            decode_record(damaged)
            self.accepted.append(name)
        except ValueError:
            self.refused[kind] += 1


class Ballast(threading.Thread):
    """A file that keeps the spool's disk full (writes fail with ENOSPC) while `full` is set: it
    takes back, every 0.1 s, what truncated or deleted files gave up meanwhile."""

    def __init__(self, disk: Path):
        super().__init__(daemon=True)
        self.path = disk / ".ballast"
        self.full, self.halt = threading.Event(), threading.Event()

    def run(self) -> None:
        while not self.halt.wait(0.1):
            if self.full.is_set():
                self.fill()

    def fill(self) -> None:
        with open(self.path, "ab", buffering=0) as f:
            for size in (1 << 16, 1 << 12, 1):  # down to the last byte: a sample's page must find none
                try:
                    while True:
                        f.write(b"\0" * size)
                except OSError as exc:
                    if exc.errno != errno.ENOSPC:
                        raise

    def remove(self) -> None:
        self.full.clear()
        time.sleep(0.2)  # a fill under way ends
        self.path.unlink(missing_ok=True)


def start(command: list[str], log: Path) -> subprocess.Popen:
    with open(log, "a") as f:
        return subprocess.Popen(command, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})


def kill_group(proc: subprocess.Popen) -> bool:
    """SIGKILL the process group; True when its leader had already ended on its own."""
    ended = proc.poll() is not None
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
    return ended


def status_of(run: Path) -> dict:
    try:
        return json.loads((run / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def census(spool: Path, damaged: dict) -> tuple[int, int]:
    """(files the decoder refuses that no saboteur touched: torn; damaged files refused) now."""
    torn = refused = 0
    for name in enumerate_spool(spool):
        try:
            data = (spool / name).read_bytes()
        except FileNotFoundError:
            continue
        try:
            decode_record(data)
        except ValueError:
            if name in damaged:
                refused += 1
            else:
                torn += 1
    return torn, refused


def checkpoint_step(run: Path) -> int | str:
    """The step --resume would continue (last.pt, or previous.pt where last.pt is damaged); 0: none."""
    for name in ("last.pt", "previous.pt"):
        if (run / name).exists():
            try:
                return load_checkpoint(run / name)["step"]
            except DamagedFile:
                continue
            except ValueError as exc:
                return f"unreadable: {exc}"
    return 0


def audit(run: Path, damaged: dict) -> dict:
    """The ledger against the saboteur's notes: steps, samples read, damaged samples read before
    their damage (the checksum written) and after it (any other: trained on damaged bytes)."""
    lines = read_ledger(run / "ledger.jsonl") if (run / "ledger.jsonl").exists() else []
    read = [(name, checksum) for line in lines for name, checksum in line["samples"]]
    before = sum(1 for name, checksum in read if name in damaged and checksum == damaged[name][1])
    after = [name for name, checksum in read if name in damaged and checksum != damaged[name][1]]
    return {"ledger_steps": len(lines), "samples_read": len(read), "damaged_read_before_damage": before,
            "damaged_samples_trained_on": len(after), "damaged_trained_names": sorted(set(after))[:10]}


def enospc_counts(log: Path) -> tuple[int, int]:
    text = log.read_text(errors="replace") if log.exists() else ""
    return len(re.findall(r"disk full under .*, backing off", text)), len(re.findall(r"space again under", text))


def mount_tmpfs(where: Path, megabytes: int) -> None:
    where.mkdir(parents=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={megabytes}m", "tmpfs", str(where)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"--tmpfs-mb {megabytes}: cannot mount a tmpfs at {where} ({done.stderr.strip()}); "
                         f"run as root, or --tmpfs-mb 0 for no full disk")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=15)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/cuboid-soak"))
    parser.add_argument("--limit", type=int, default=300)
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--checkpoint-every", type=int, default=3)
    parser.add_argument("--short", type=float, nargs=2, default=(0.3, 2.0), help="a short cycle kills after this many s")
    parser.add_argument("--long", type=float, nargs=2, default=(6.0, 14.0), help="a long cycle kills after this many s")
    parser.add_argument("--long-share", type=float, default=0.3, help="share of the cycles that are long")
    parser.add_argument("--max-rate", type=float, default=50.0, help="the generator's samples/s (0: as fast as it can)")
    parser.add_argument("--sabotage-every", type=float, default=0.3, help="s between damaged samples (0: none)")
    parser.add_argument("--tmpfs-mb", type=int, default=8, help="the spool's disk (0: the workdir's, never full)")
    parser.add_argument("--full-share", type=float, default=0.2, help="share of the cycles with the spool's disk full")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    rng = random.Random(args.seed)
    if args.workdir.exists():
        subprocess.run(["umount", str(args.workdir / "spool")], capture_output=True)
        shutil.rmtree(args.workdir)
    spool, run, logs = args.workdir / "spool", args.workdir / "run", args.workdir / "logs"
    logs.mkdir(parents=True)
    if args.tmpfs_mb:
        mount_tmpfs(spool, args.tmpfs_mb)
    try:
        report = soak(args, rng, spool, run, logs)
    finally:
        if args.tmpfs_mb:
            subprocess.run(["umount", "-l", str(spool)], capture_output=True)
    print(json.dumps(report, indent=2))


@dataclass
class Daemons:
    """The two daemons' commands and their processes now (each restart replaces its process)."""

    generate: list[str]
    train: list[str]
    run: Path  # the trainer's --out
    generator: subprocess.Popen | None = None
    trainer: subprocess.Popen | None = None

    def resume(self) -> list[str]:
        return ["--resume"] if (self.run / "last.pt").exists() else []


@dataclass
class Tally:
    """What the cycles counted, for the report."""

    cycles: list[dict] = field(default_factory=list)
    checkpoint_steps: list[int] = field(default_factory=lambda: [0])
    trainer_skips: Counter = field(default_factory=Counter)
    needed_a_hand: Counter = field(default_factory=Counter)
    trained: int = 0  # steps the killed trainers had trained past their checkpoint
    freed_at: list[int] = field(default_factory=list)  # samples published when each full spell ended
    started_at: float = field(default_factory=time.time)


def soak(args, rng: random.Random, spool: Path, run: Path, logs: Path) -> dict:
    generate = [sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(spool), "--limit", str(args.limit),
                "--size", str(args.size), "--workers", "1", "--no-dashboard"]
    generate += ["--max-rate", str(args.max_rate)] if args.max_rate else []
    train = [sys.executable, "-m", "cuboidtrain", "run", "--spool", str(spool), "--size", str(args.size),
             "--arch", "tiny", "--batch-size", str(args.batch_size), "--threads", "1", "--loader-workers", "1",
             "--out", str(run), "--checkpoint-every", str(args.checkpoint_every), "--log-every", "1",
             "--ledger", "--no-dashboard"]
    daemons = Daemons(generate, train, run)
    daemons.generator = start(daemons.generate, logs / "generator.log")
    while len(enumerate_spool(spool)) < 4 * args.batch_size:
        time.sleep(0.1)
    watch, saboteur, ballast = SpoolWatch(spool), Saboteur(spool, args.sabotage_every, rng), Ballast(spool)
    watch.start()
    ballast.start()
    if args.sabotage_every:
        saboteur.start()
    daemons.trainer = start(daemons.train, logs / "trainer.log")
    full, tally = full_cycles(args, rng), Tally()
    for cycle in range(args.cycles):
        if args.tmpfs_mb and cycle in full and cycle - 1 not in full:
            ballast.full.set()
        if cycle not in full and cycle - 1 in full:
            ballast.remove()
            tally.freed_at.append(watch.published())
        long = rng.random() < args.long_share
        time.sleep(rng.uniform(*(args.long if long else args.short)))
        record = kill_and_restart(rng.choice(["trainer", "generator", "both"]), daemons, tally, spool, logs, saboteur)
        record |= {"cycle": cycle, "long": long, "disk_full": cycle in full}
        tally.cycles.append(record)
        print(json.dumps(record), flush=True)
    ballast.remove()
    return final_report(args, spool, logs, daemons, tally, watch, saboteur, ballast)


def kill_and_restart(victim: str, daemons: Daemons, tally: Tally, spool: Path, logs: Path, saboteur: Saboteur) -> dict:
    """One cycle's kill: SIGKILL to `victim` ("trainer", "generator" or "both"), what it left, its restart."""
    run, before = daemons.run, status_of(daemons.run)
    record = {"killed": victim}
    if victim in ("trainer", "both"):
        tally.needed_a_hand["trainer"] += kill_group(daemons.trainer)
    if victim in ("generator", "both"):
        tally.needed_a_hand["generator"] += kill_group(daemons.generator)
    time.sleep(0.2)
    record["torn"], record["damaged_in_spool_refused"] = census(spool, saboteur.damaged)
    if victim in ("trainer", "both"):
        kept = tally.checkpoint_steps[-1]
        ours = before.get("pid") == daemons.trainer.pid  # the killed trainer had started and reported
        record["trainer_step_at_kill"] = before.get("step") if ours else None
        record["resumed_and_trained"] = bool(ours and before.get("step", 0) > kept)
        if ours:
            tally.trainer_skips.update(before.get("skipped") or {})
            tally.trained += max(0, before.get("step", 0) - kept)
        step = checkpoint_step(run)
        record["checkpoint"] = step
        record["step_went_back"] = isinstance(step, int) and step < kept
        tally.checkpoint_steps.append(step if isinstance(step, int) else -1)
        daemons.trainer = start(daemons.train + daemons.resume(), logs / "trainer.log")
    if victim in ("generator", "both"):
        daemons.generator = start(daemons.generate, logs / "generator.log")
    return record


def full_cycles(args, rng: random.Random) -> set[int]:
    """Two runs of cycles, together --full-share of them, in which the spool's disk is held full."""
    span = int(args.cycles * args.full_share / 2)
    if span == 0:
        return set()
    starts = (args.cycles // 4, (args.cycles * 5) // 8)
    return {c for first in starts for c in range(first, min(first + span, args.cycles))}


def final_report(args, spool: Path, logs: Path, daemons: Daemons, tally: Tally, watch: SpoolWatch, saboteur: Saboteur,
                 ballast: Ballast) -> dict:
    """The end: the trainer finishes a --resume run a few steps past its checkpoint, the generator stops cleanly."""
    run, cycles = daemons.run, tally.cycles
    saboteur.halt.set()
    ballast.halt.set()
    kill_group(daemons.trainer)
    final_from = checkpoint_step(run)
    final_from = final_from if isinstance(final_from, int) else 0
    final = subprocess.run(daemons.train + daemons.resume() + ["--steps", str(final_from + 4)], cwd=ROOT,
                           capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})
    final_status = status_of(run)
    tally.trainer_skips.update(final_status.get("skipped") or {})
    daemons.generator.send_signal(signal.SIGTERM)
    daemons.generator.wait(timeout=60)
    watch.halt.set()
    watch.join()
    torn_end, refused_end = census(spool, saboteur.damaged)
    trainer_kills = [c for c in cycles if "checkpoint" in c]
    backoffs, recoveries = enospc_counts(logs / "generator.log")
    kinds = Counter(kind for kind, _ in saboteur.damaged.values())
    return {
        "cycles": args.cycles, "seconds": round(time.time() - tally.started_at), "limit": args.limit, "size": args.size,
        "kills": dict(Counter(c["killed"] for c in cycles)),
        "cycles_with_the_disk_full": sum(c["disk_full"] for c in cycles),
        "samples_published_at_least": watch.published(),
        "files_damaged": {"all": len(saboteur.damaged), **kinds},
        "damaged_refused_by_the_decoder": dict(saboteur.refused),
        "damaged_accepted_by_the_decoder": len(saboteur.accepted),
        "damaged_in_the_spool_at_the_end_refused": refused_end,
        "trainer_skipped": dict(tally.trainer_skips),
        **audit(run, saboteur.damaged),
        "torn": sum(c["torn"] for c in cycles) + torn_end,
        "lost_published": len(watch.lost),
        "restarts_that_needed_a_hand": dict(tally.needed_a_hand),
        "checkpoints_lost": sum(isinstance(c["checkpoint"], str) or c["step_went_back"] for c in trainer_kills),
        "trainer_restarts": len(trainer_kills),
        "restarts_that_trained_past_their_checkpoint": sum(c["resumed_and_trained"] for c in trainer_kills),
        "steps_trained_between_kills": tally.trained,
        "enospc_backoffs": backoffs, "enospc_recoveries_logged": recoveries,
        "full_spells_after_which_publishing_resumed": f"{sum(watch.published() > n for n in tally.freed_at)} of "
                                                      f"{len(tally.freed_at)}",
        "sabotage_refused_by_a_full_disk": saboteur.no_space,
        "final_resume": {"exit": final.returncode, "from_step": final_from, "state": final_status.get("state"),
                         "step": final_status.get("step")},
    }


if __name__ == "__main__":
    main()
