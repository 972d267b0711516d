"""Trainer throughput beside a full-speed generator against a frozen spool (issue 14).

One trainer process per variant trains on a spool that a generator keeps rotating; the
generator is paused (SIGSTOP to its process group: a frozen spool, nothing published)
and resumed (SIGCONT: full speed) in alternating windows, so both conditions run in
the same trainer process, interleaved. Per window: samples/s, data wait (the trainer's
own per-step fetch wait over step time), samples published. Variants:

* listing: the trainer as shipped; the spool's count and rate come from its listings
  (cuboidtrain.data.census.SpoolCensus);
* watchdog: the same trainer with the watchdog/inotify watcher it had before (copied
  here unchanged), for comparison.

Then the throttle: a trainer beside a generator with --max-rate at half the trainer's
frozen samples/s, on a small spool, for a few epochs: evicted unread should be 0.

Fair on 2 cores: the trainer (one torch thread, one loader worker) is pinned to the first
core, the generator (one worker: its default is one per core) to the second, so "full
speed" is the generator's full speed on the core it is given, and the trainer has the same
core in both conditions. Medians over windows; ratios live/frozen within one trainer process.

    nice -n 5 .venv/bin/python benchmarks/soak/bench_spool_live.py --json bench-live.json
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from cuboidtrain.data.census import highest_sequences, published_between  # noqa: E402
from shared.spool import enumerate_spool, is_sample_name  # noqa: E402


# ---- the watcher the trainer had before issue 14 (cuboidtrain/train/spoolwatch.py at 43d53fe)


def watchdog_census(spool):
    from watchdog.events import FileSystemEventHandler
    from watchdog.observers import Observer

    class SpoolWatcher(FileSystemEventHandler):
        def __init__(self, spool):
            super().__init__()
            self.spool = Path(spool)
            self._lock = threading.Lock()
            self._count = len(enumerate_spool(self.spool))
            self._arrivals = 0
            self._since = time.monotonic()
            self._observer = Observer()
            self._observer.schedule(self, str(self.spool), recursive=False)
            self._observer.start()
            # it did not count evicted samples: zeros here, "not counted" in the table
            self.evicted_unread, self.evicted_unread_total = {"never_listed": 0, "vanished": 0, "abandoned": 0}, 0

        def on_moved(self, event):
            if is_sample_name(os.path.basename(event.dest_path)):
                self._add(1, arrived=True)

        def on_created(self, event):
            if is_sample_name(os.path.basename(event.src_path)):
                self._add(1, arrived=True)

        def on_deleted(self, event):
            if is_sample_name(os.path.basename(event.src_path)):
                self._add(-1)

        def _add(self, delta, arrived=False):
            with self._lock:
                self._count = max(0, self._count + delta)
                self._arrivals += arrived

        @property
        def count(self):
            return self._count

        def arrivals_per_s(self):
            with self._lock:
                now = time.monotonic()
                rate = self._arrivals / max(now - self._since, 1e-9)
                self._arrivals, self._since = 0, now
            return rate

        # what train.py asks of a census now
        def listed(self, names):
            with self._lock:
                self._count = len(names)
            return {}

        def read(self, names):
            pass

    return SpoolWatcher(spool)


# ---- the trainer (a child process)


def child(args) -> None:
    import cuboidtrain.train.monitor.progress as progress
    import cuboidtrain.train.loop as train
    from cuboidtrain.train.config import TrainConfig

    if args.child == "watchdog":
        train.SpoolCensus = watchdog_census
    log = open(args.steps_log, "a", buffering=1)
    original = progress.Progress.step

    def step(self, step, losses, samples, waited, *rest):  # every step: when it ended, its fetch wait
        log.write(json.dumps([time.time(), waited, samples]) + "\n")
        return original(self, step, losses, samples, waited, *rest)

    progress.Progress.step = step
    config = TrainConfig(spool=args.spool, out=args.out, shape="box", size=args.size, arch=args.arch, reframe=args.reframe,
                         batch_size=args.batch_size, threads=1, loader_workers=1, checkpoint_every=10**9,
                         log_every=10**6, dashboard=False)
    train.run(config)


# ---- the parent


def start(command: list[str], log: Path, cores: set[int] | None = None) -> subprocess.Popen:
    """`cores`: the CPUs it and its children may run on (the trainer one core, the generator the other)."""
    pin = (lambda: os.sched_setaffinity(0, cores)) if cores else None
    with open(log, "a") as f:
        return subprocess.Popen(command, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}, preexec_fn=pin)


def cores(role: str) -> set[int] | None:
    """With two cores or more: the trainer on the first, the generator on the second."""
    available = sorted(os.sched_getaffinity(0))
    if len(available) < 2:
        return None
    return {available[0]} if role == "trainer" else {available[1]}


def generator(spool: Path, args, log: Path, *extra: str) -> subprocess.Popen:
    return start([sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(spool), "--size", str(args.size),
                  "--workers", "1", "--no-dashboard", *extra], log, cores("generator"))


def trainer(variant: str, spool: Path, out: Path, args, log: Path) -> tuple[subprocess.Popen, Path]:
    steps = out.with_suffix(".steps.jsonl")
    return start([sys.executable, __file__, "--child", variant, "--spool", str(spool), "--out", str(out),
                  "--steps-log", str(steps), "--size", str(args.size), "--arch", args.arch,
                  "--batch-size", str(args.batch_size), "--reframe" if args.reframe else "--no-reframe"],
                 log, cores("trainer")), steps


def signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def stop(proc: subprocess.Popen) -> None:
    signal_group(proc, signal.SIGCONT)
    signal_group(proc, signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        signal_group(proc, signal.SIGKILL)
        proc.wait()


def steps_of(path: Path) -> list[list[float]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except OSError:
        return []


def wait_for_steps(path: Path, count: int, deadline: float) -> None:
    end = time.monotonic() + deadline
    while len(steps_of(path)) < count:
        if time.monotonic() > end:
            raise SystemExit(f"the trainer made fewer than {count} steps in {deadline:.0f} s (see its log)")
        time.sleep(0.5)


def status_of(out: Path) -> dict:
    try:
        return json.loads((out / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def group_cpu(pgid: int) -> dict[str, float]:
    """CPU seconds (user + system) of the processes in a process group: the group's leader
    (the trainer's main process) apart from the rest (its loader worker)."""
    tick = os.sysconf("SC_CLK_TCK")
    leader = others = 0.0
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = open(f"/proc/{entry}/stat").read().rpartition(")")[2].split()
        except OSError:
            continue
        if int(fields[2]) != pgid:  # fields after the name: state, ppid, pgrp, ...
            continue
        seconds = (int(fields[11]) + int(fields[12])) / tick  # utime, stime
        if int(entry) == pgid:
            leader += seconds
        else:
            others += seconds
    return {"main": leader, "workers": others}


def core_times(core: int) -> dict[str, float]:
    """Seconds core `core` spent in each state since boot (/proc/stat), for the kernel's share."""
    tick = os.sysconf("SC_CLK_TCK")
    for line in open("/proc/stat"):
        if line.startswith(f"cpu{core} "):
            values = [int(v) / tick for v in line.split()[1:9]]
            return dict(zip(("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal"), values))
    return {}


def difference(after: dict, before: dict) -> dict:
    return {k: round(after[k] - before.get(k, 0.0), 3) for k in after}


def window_figures(steps: list[list[float]], start: float, end: float) -> dict:
    inside = [s for s in steps if start < s[0] <= end]
    previous = [s[0] for s in steps if s[0] <= start]
    times = ([previous[-1]] if previous else []) + [s[0] for s in inside]
    spans = [b - a for a, b in zip(times, times[1:])]
    inside = inside[-len(spans):] if spans else []
    span = sum(spans)
    return {"steps": len(inside), "samples_per_s": sum(s[2] for s in inside) / span if span else None,
            "data_wait": sum(s[1] for s in inside) / span if span else None}


def run_variant(variant: str, args, work: Path) -> dict:
    spool, logs = work / "spool", work / "logs"
    out = work / f"run-{variant}"
    known = highest_sequences(enumerate_spool(spool)) if spool.is_dir() else {}
    gen = generator(spool, args, logs / "generator.log", "--limit", str(args.limit))
    # full, and this generator's worker publishing (not still starting) before it is paused
    while (not spool.is_dir() or len(enumerate_spool(spool)) < args.limit
           or published_between(known, highest_sequences(enumerate_spool(spool))) < 50):
        time.sleep(0.5)
    signal_group(gen, signal.SIGSTOP)
    proc, steps_path = trainer(variant, spool, out, args, logs / f"trainer-{variant}.log")
    windows, trainer_core = [], min(cores("trainer") or {0})  # the core whose kernel time is counted
    try:
        wait_for_steps(steps_path, args.warmup_steps, 600)
        for pair in range(args.pairs):
            # alternate which condition comes first, so a drift in the machine's load splits evenly
            for live in ((True, False) if pair % 2 == 0 else (False, True)):
                signal_group(gen, signal.SIGCONT if live else signal.SIGSTOP)
                before, began = highest_sequences(enumerate_spool(spool)), time.time()
                unread_before = status_of(out).get("spool_evicted_unread")
                cpu_before, core_before = group_cpu(proc.pid), core_times(trainer_core)
                time.sleep(args.window)
                ended = time.time()
                cpu = difference(group_cpu(proc.pid), cpu_before)
                core = difference(core_times(trainer_core), core_before)
                published = published_between(before, highest_sequences(enumerate_spool(spool)))
                windows.append({"live": live, "published_per_s": published / (ended - began),
                                "evicted_unread_so_far": status_of(out).get("spool_evicted_unread"),
                                "evicted_unread_at_start": unread_before, "began": began, "ended": ended,
                                "trainer_cpu_s": cpu, "trainer_core_s": core,
                                "epochs_so_far": status_of(out).get("epoch")})
    finally:
        signal_group(gen, signal.SIGSTOP)
        stop(proc)
        stop(gen)
    steps = steps_of(steps_path)
    for w in windows:
        w.update(window_figures(steps, w["began"], w["ended"]))
    final = status_of(out)
    live = [w for w in windows if w["live"]]
    frozen = [w for w in windows if not w["live"]]
    pairs = [(a, b) for a, b in zip(live, frozen) if a["samples_per_s"] and b["samples_per_s"]]
    return {
        "variant": variant,
        "frozen_samples_per_s": statistics.median(w["samples_per_s"] for w in frozen),
        "live_samples_per_s": statistics.median(w["samples_per_s"] for w in live),
        "ratio_live_over_frozen": statistics.median(a["samples_per_s"] / b["samples_per_s"] for a, b in pairs),
        "frozen_data_wait": statistics.median(w["data_wait"] for w in frozen),
        "live_data_wait": statistics.median(w["data_wait"] for w in live),
        "published_per_s_live": statistics.median(w["published_per_s"] for w in live),
        # where the trainer's core went, per window second: its main process, its loader worker, the kernel
        **{f"{name}_core_share_{cond}": statistics.median(share(w) for w in ws)
           for cond, ws in (("frozen", frozen), ("live", live))
           for name, share in (("main", lambda w: w["trainer_cpu_s"]["main"] / (w["ended"] - w["began"])),
                               ("loader", lambda w: w["trainer_cpu_s"]["workers"] / (w["ended"] - w["began"])),
                               ("system", lambda w: w["trainer_core_s"]["system"] / (w["ended"] - w["began"])))},
        "evicted_unread_total": final.get("spool_evicted_unread"),
        "skipped": final.get("skipped"),
        "windows": windows,
    }


def run_throttled(args, work: Path, trainer_rate: float) -> dict:
    """A generator held to half the trainer's frozen rate, a spool it turns over in a few epochs."""
    spool, logs, out = work / "spool-throttled", work / "logs", work / "run-throttled"
    fill = generator(spool, args, logs / "generator-throttled.log", "--limit", str(args.small_limit),
                     "--max-samples", str(args.small_limit))
    fill.wait()
    rate = trainer_rate / 2
    gen = generator(spool, args, logs / "generator-throttled.log", "--limit", str(args.small_limit),
                    "--max-rate", f"{rate:.3f}")
    before = highest_sequences(enumerate_spool(spool))
    proc, steps_path = trainer("listing", spool, out, args, logs / "trainer-throttled.log")
    epochs_wanted = args.throttle_epochs
    began = time.time()
    try:
        deadline = time.monotonic() + args.throttle_max_s
        while status_of(out).get("epoch", 0) < epochs_wanted and time.monotonic() < deadline:
            time.sleep(1)
    finally:
        stop(proc)
        published = published_between(before, highest_sequences(enumerate_spool(spool)))
        stop(gen)
    final = status_of(out)
    seconds = time.time() - began
    return {"max_rate": rate, "limit": args.small_limit, "seconds": seconds, "epochs_listed": final.get("epoch"),
            "published": published, "trained_samples": final.get("step", 0) * args.batch_size,
            "evicted_unread_total": final.get("spool_evicted_unread"), "skipped": final.get("skipped")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--child", choices=("listing", "watchdog"), help=argparse.SUPPRESS)
    parser.add_argument("--spool", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--steps-log", help=argparse.SUPPRESS)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--arch", default="paper")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--reframe", action=argparse.BooleanOptionalAction, default=True,
                        help="frame every sample as infer does (the trainer's default; its loader's heavier case)")
    parser.add_argument("--limit", type=int, default=10_000, help="the spool's cap (cuboidgen's default)")
    parser.add_argument("--window", type=float, default=20.0, help="s per window")
    parser.add_argument("--pairs", type=int, default=3, help="live/frozen window pairs per variant")
    parser.add_argument("--warmup-steps", type=int, default=5)
    parser.add_argument("--variants", nargs="+", default=["listing", "watchdog"], choices=("listing", "watchdog"))
    parser.add_argument("--small-limit", type=int, default=400, help="the throttled run's spool cap")
    parser.add_argument("--throttle-epochs", type=int, default=4)
    parser.add_argument("--throttle-max-s", type=float, default=240)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/cuboid-live"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.child:
        return child(args)
    for name in ("window", "pairs", "limit", "small_limit"):
        if getattr(args, name) <= 0:
            raise SystemExit(f"--{name.replace('_', '-')} {getattr(args, name)}: expected a positive number")
    shutil.rmtree(args.workdir, ignore_errors=True)
    (args.workdir / "logs").mkdir(parents=True)
    started = time.time()
    variants = [run_variant(v, args, args.workdir) for v in args.variants]
    listing = next((v for v in variants if v["variant"] == "listing"), variants[0])
    throttled = run_throttled(args, args.workdir, listing["frozen_samples_per_s"])
    print(f"{'variant':10s} {'frozen/s':>9s} {'live/s':>9s} {'live/frozen':>11s} {'wait frozen':>11s} "
          f"{'wait live':>9s} {'published/s':>11s} {'evicted unread':>14s}")
    for v in variants:
        print(f"{v['variant']:10s} {v['frozen_samples_per_s']:9.2f} {v['live_samples_per_s']:9.2f} "
              f"{v['ratio_live_over_frozen']:11.1%} {v['frozen_data_wait']:11.1%} {v['live_data_wait']:9.1%} "
              f"{v['published_per_s_live']:11.0f} "
              f"{str(v['evicted_unread_total']) if v['variant'] == 'listing' else 'not counted':>14s}")
    t = throttled
    for v in variants:
        print(f"{v['variant']}: the trainer's core, frozen / live: main process "
              f"{v['main_core_share_frozen']:.0%} / {v['main_core_share_live']:.0%}, loader worker "
              f"{v['loader_core_share_frozen']:.0%} / {v['loader_core_share_live']:.0%}, kernel "
              f"{v['system_core_share_frozen']:.0%} / {v['system_core_share_live']:.0%}")
    print(f"throttled: --max-rate {t['max_rate']:.2f}/s, limit {t['limit']}: {t['published']} published, "
          f"{t['trained_samples']} trained on, {t['epochs_listed']} epochs, evicted unread {t['evicted_unread_total']}")
    result = {"settings": {k: v for k, v in vars(args).items() if k not in ("child", "spool", "out", "steps_log")},
              "seconds": round(time.time() - started), "variants": variants, "throttled": throttled}
    text = json.dumps(result, indent=2, default=str)
    if args.json:
        args.json.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
