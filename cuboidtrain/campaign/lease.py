"""One lease, in one command: smoke check, generators, the standing run resumed until the deadline,
the new state and a log row into OUT, then the evaluation.

OUT (what the device returns: at most 8 files of 16 MiB) receives the state's parts
(`SHAPE.state.NN`), `lease.json` (the log row and the state's manifest) and `eval.json` (the
campaign's and the shipped models' bench_accuracy figures). The state is written before the
evaluation starts, so a lease cut short at its end still returns its training.
`cuboidtrain campaign apply` takes them into campaign/ (cuboidtrain.campaign.apply).
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from cuboidtrain.campaign.evaluation import (SHIPPED_EVAL, bench, compare, evaluation_record, pack_models,
                                             shipped_figures, shipped_models)
from cuboidtrain.campaign.plan import CampaignPlan, load_plan
from cuboidtrain.campaign.smoke import smoke_check
from cuboidtrain.campaign.state import read_log, read_state, restore, state_digest, store
from cuboidtrain.campaign.training import Course, train_until
from cuboidtrain.models.zoo import git_commit
from shared.errors import UsageError
from shared.files import json_text, write_json

log = logging.getLogger(__name__)

LEASE = "lease.json"
EVAL = "eval.json"
STAMP = "%Y-%m-%dT%H:%M:%SZ"  # a log row's and an evaluation's date, UTC
# The generator as a process of this interpreter: the lent machine has the project on PYTHONPATH, not installed.
CUBOIDGEN = [sys.executable, "-c", "import sys; from cuboidgen.cli import main; sys.argv[0] = 'cuboidgen'; main()"]
# Stopping the trainers and packing the state into OUT: 6-9 s past the training's deadline on the lent machine (leases 3-5)
STORE_MINUTES = 0.25
SEED_BASE = 1_000_000  # the generators' seeds: LEASE * 100 + shape * 10 + scene above it, clear of every recipe's and bench's


@dataclass(frozen=True)
class LeaseOptions:
    out: Path  # the folder the device returns ($OUT)
    campaign: Path = Path("campaign")
    work: Path = Path("/tmp/campaign-work")
    minutes: float = 9.5  # the whole command, smoke check to the last file (the device allows 10)
    device: str = "cuda"
    lease_steps: int | None = None  # at most this many steps a shape (a deterministic stop, for tests)
    spool: Path | None = None  # one frozen spool for every shape instead of generators (tests)
    evaluate: bool = True
    commit: str | None = None
    threads: int | None = None  # each trainer's torch threads
    eval_threads: int | None = None  # bench_accuracy's; None: 4 (small models gain little from more)


def run_lease(options: LeaseOptions) -> dict:
    """The lease's log row, once its state (and, time allowing, its evaluation) is in OUT."""
    started, clock = time.monotonic(), dt.datetime.now(dt.timezone.utc)
    deadline = started + options.minutes * 60
    plan, campaign = load_plan(options.campaign), Path(options.campaign)
    state, lease, base = read_state(campaign), len(read_log(campaign)) + 1, state_digest(campaign)
    # 1. smoke: the device, the imports, one step; seconds, and one line if it fails
    device_name = smoke_check(plan, options.device)
    log.info("lease %d of the campaign (%s %d px, %s): %s; deadline in %.1f min", lease, plan.arch, plan.size,
             "+".join(plan.shapes), device_name, options.minutes)
    out, work = Path(options.out), Path(options.work)
    out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    courses = [restored_course(plan, campaign, state, shape, work, options.lease_steps) for shape in plan.shapes]
    # 2. generators on the cores the trainers leave; 3. training until the deadline less what follows it
    spools = {shape: options.spool or work / "spools" / f"train-{shape}" for shape in plan.shapes}
    generators = [] if options.spool else start_generators(plan, spools, work, lease)
    train_started = time.monotonic()
    try:
        train_until(plan, courses, spools, options.device, deadline - reserved_minutes(plan, options.evaluate) * 60,
                    options.threads,
                    log_every=1 if options.lease_steps is not None and options.lease_steps < 100 else 10)
    finally:
        stop_all(generators)
    trained_s = time.monotonic() - train_started
    # 4. the state and the row into OUT, before the evaluation
    checkpoints = {c.shape: c.newest for c in courses if c.newest is not None}
    entries = store(checkpoints, plan, out)
    row = lease_row(plan, lease, base, clock, device_name, options.commit or git_commit(), courses, entries, trained_s)
    write_lease(out, row, entries)
    # 5. the evaluation, in the time left
    if options.evaluate and checkpoints:
        try:
            scored = evaluate(plan, campaign, checkpoints, work, out, lease, deadline, options.eval_threads)
            row["eval"] = compare(scored["campaign"], scored["shipped"])
        except Exception as error:  # the training is in OUT already: a failed score must not cost the lease
            log.warning("lease %d: the evaluation failed (%s: %s); `cuboidtrain campaign evaluate` scores the "
                        "state once applied", lease, type(error).__name__, error)
            row["eval"] = {"failed": f"{type(error).__name__}: {error}"}
        row["minutes"] = round((time.monotonic() - started) / 60, 2)
        write_lease(out, row, entries)
    log.info("lease %d: %s", lease, json_text(row))
    return row


def reserved_minutes(plan: CampaignPlan, evaluate: bool) -> float:
    """The lease's minutes kept after training: the plan's eval_minutes (stopping, packing, evaluating) when it
    evaluates, else only the packing's (leases 3-5 ran --no-evaluate and still stopped 1.25 minutes early,
    a third of lease 4's training)."""
    return plan.eval_minutes if evaluate else STORE_MINUTES


def restored_course(plan: CampaignPlan, campaign: Path, state: dict, shape: str, work: Path,
                    lease_steps: int | None) -> Course:
    """The shape's run as the campaign left it: its checkpoint restored into WORK/SHAPE/pPHASE/last.pt,
    or the plan's first phase from scratch (the first lease: no weights committed before it)."""
    if shape not in state:
        return Course(shape, work, plan.phases[0], 0, resume=False, steps_left=lease_steps)
    entry = state[shape]
    phase = plan.phase(entry.phase)
    course = Course(shape, work, phase, entry.step, resume=True, steps_left=lease_steps)
    restore(campaign, entry, course.folder / "last.pt")
    if entry.step >= phase.steps:  # the phase ended with the last lease: the next starts from its weights
        course.init, course.phase, course.step, course.resume = course.folder / "last.pt", plan.phase_after(phase.phase), 0, False
    return course


def start_generators(plan: CampaignPlan, spools: dict[str, Path], work: Path, lease: int) -> list[subprocess.Popen]:
    """One generator per shape and scene, fresh seeds each lease (no lease trains on another's samples)."""
    gens = len(plan.shapes) * len(plan.scenes)
    left = (os.cpu_count() or 1) - len(plan.shapes) * (1 + plan.loader_workers)
    workers = plan.generator_workers or max(1, left // gens)
    processes = []
    for i, shape in enumerate(plan.shapes):
        for j, scene in enumerate(plan.scenes):
            seed = SEED_BASE + lease * 100 + i * 10 + j
            command = CUBOIDGEN + ["run", "--spool", str(spools[shape]), "--shape", shape, "--size", str(plan.generator_size),
                                   "--scene", scene, "--limit", str(plan.spool_limit), "--seed", str(seed),
                                   "--workers", str(workers), "--no-dashboard"]
            logfile = open(work / f"generator-{shape}-{scene}.log", "w")
            processes.append(subprocess.Popen(command, stdout=logfile, stderr=subprocess.STDOUT))
    log.info("%d generators of %d workers each (%d cores)", len(processes), workers, os.cpu_count() or 1)
    return processes


def stop_all(processes: list[subprocess.Popen], grace_s: float = 15.0) -> None:
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    end = time.monotonic() + grace_s
    for process in processes:
        try:
            process.wait(timeout=max(end - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def lease_row(plan: CampaignPlan, lease: int, base: str, clock: dt.datetime, device: str, commit: str | None,
              courses: list[Course], entries: dict, trained_s: float) -> dict:
    """The log's row: date, device, commit, minutes trained, steps, samples/s (all shapes together), data wait
    (the worst shape's share of step time), each shape's own, and the evaluation (added after)."""
    shapes = {}
    for course in courses:
        segs = course.segments
        seconds = sum(s.seconds for s in segs)
        rates = [(s.seconds, s.samples_per_s, s.data_wait) for s in segs if s.samples_per_s is not None]
        weight = sum(r[0] for r in rates)
        entry = entries.get(course.shape)
        shapes[course.shape] = {
            "steps": sum(s.to_step - s.from_step for s in segs),
            "from": [segs[0].phase, segs[0].from_step] if segs else None,
            "to": [entry.phase, entry.step] if entry else None,
            "samples_seen": entry.samples_seen if entry else 0,
            "minutes": round(seconds / 60, 2),
            "samples_per_s": round(sum(r[0] * r[1] for r in rates) / weight, 1) if weight else None,
            "data_wait": round(sum(r[0] * r[2] for r in rates) / weight, 4) if weight else None,
            "failed": next((s.failed for s in segs if s.failed), None),
        }
    known = [s for s in shapes.values() if s["samples_per_s"] is not None]
    return {"lease": lease, "date": clock.strftime(STAMP), "device": device, "commit": commit,
            "arch": plan.arch, "size": plan.size, "minutes_trained": round(trained_s / 60, 2),
            "steps": sum(s["steps"] for s in shapes.values()),
            "samples_per_s": round(sum(s["samples_per_s"] for s in known), 1) if known else None,
            "data_wait": round(max(s["data_wait"] for s in known), 4) if known else None,
            "shapes": shapes, "eval": None, "base": base}


def write_lease(out: Path, row: dict, entries: dict) -> Path:
    path = out / LEASE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json_text({"row": row, "state": {s: vars(e) for s, e in entries.items()}}, indent=2, default=list) + "\n")
    os.replace(tmp, path)
    return path


def evaluate_state(campaign: Path, work: Path, threads: int | None, timeout_s: float = 3600.0) -> dict:
    """The standing state's models and the shipped ones on the lease's masks, here (`cuboidtrain campaign
    evaluate`): for a lease whose own evaluation was cut off or failed. Writes campaign/eval.json, the
    figures with the lease they belong to; returns its content."""
    plan, campaign, work = load_plan(campaign), Path(campaign), Path(work)
    state, leases = read_state(campaign), len(read_log(campaign))
    if not state:
        raise UsageError(f"{campaign}: no state yet (no lease applied): nothing to evaluate")
    shutil.rmtree(work, ignore_errors=True)
    (work / "out").mkdir(parents=True)
    checkpoints = {shape: restore(campaign, entry, work / shape / "last.pt") for shape, entry in state.items()}
    scored = evaluate(plan, campaign, checkpoints, work, work / "out", leases, time.monotonic() + timeout_s, threads)
    record = evaluation_record(leases, {s: [e.phase, e.step] for s, e in state.items()}, platform.node() or "here",
                               dt.datetime.now(dt.timezone.utc).strftime(STAMP),
                               compare(scored["campaign"], scored["shipped"]), scored)
    write_json(campaign / EVAL, record, indent=1)
    return record


def evaluate(plan: CampaignPlan, campaign: Path, checkpoints: dict[str, Path], work: Path, out: Path, lease: int,
             deadline: float, threads: int | None) -> dict:
    """The campaign's models and the shipped ones on bench_accuracy's sets: eval.json in OUT, and its content
    (`campaign`, `shipped`, `shipped_from`; `evaluation.compare` sums it up for the log row). The shipped
    models are scored only where no earlier lease kept their figures (the first lease), beside the
    campaign's, each bench in its own process on its own copy of the seeded masks (the same masks)."""
    threads = threads or min(4, os.cpu_count() or 1)
    models = pack_models(checkpoints, plan, work / "models", recipe=f"cuboidtrain campaign lease {lease} ({plan.arch} {plan.size} px)")
    kept = shipped_figures(campaign, plan)
    runs = {"campaign": models} | ({} if kept else {"shipped": shipped_models(plan)})
    with ThreadPoolExecutor(len(runs)) as pool:  # each thread waits on its own bench process
        benched = {who: pool.submit(bench, files, plan.eval_samples, work / f"eval-spools-{who}", threads,
                                    deadline - time.monotonic() - 5, work / f"bench-{who}.json")
                   for who, files in runs.items()}
    scored = {"campaign": benched["campaign"].result(), "shipped": kept or benched["shipped"].result(),
              "shipped_from": SHIPPED_EVAL if kept else "this lease"}
    write_json(out / EVAL, scored, indent=1)
    return scored
