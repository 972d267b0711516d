"""A lease's training: each shape's standing run resumed, phase after phase, until the deadline.

Each shape trains in its own `cuboidtrain run` process, side by side on the one device, resumed
from the state restored into WORK/SHAPE/pPHASE/last.pt (`--resume`: weights, optimizer, step,
loader position, RNG). A phase's cosine runs over the plan's steps for that phase, across
leases; the lease's share ends at the deadline (`--max-minutes`) or, for a deterministic test,
after `lease_steps` steps (`--stop-at`). A phase that reaches its steps hands its weights to the
next (`--init`) while time is left.
"""
from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from cuboidtrain.campaign.plan import CampaignPlan, PhasePlan
from cuboidtrain.train.monitor.status import read_status

log = logging.getLogger(__name__)

LEAST_PHASE_S = 30.0  # s: a next phase starts only with at least this much of the lease left
OVERRUN_S = 30.0  # s past its deadline a trainer is asked to stop (SIGTERM), and as long again before it is killed: the state must be written inside the command's 10 minutes
STARTUP_S = 15.0  # s: a trainer's start (imports, CUDA, loader workers) before its --max-minutes clock starts
CHECKPOINT_EVERY = 500  # steps: a trainer killed mid-lease loses at most this many (about a minute on an H100)


@dataclass(frozen=True)
class Segment:
    """One trainer process of the lease: a phase from one step to another, and its pace."""

    phase: str
    from_step: int
    to_step: int
    seconds: float
    samples_per_s: float | None
    data_wait: float | None
    failed: str | None = None


@dataclass
class Course:
    """One shape's way through the lease (the loop's own bookkeeping): where its run stands, the
    process training it now, and the segments done."""

    shape: str
    work: Path  # the lease's work folder: each phase trains in WORK/SHAPE/pPHASE
    phase: PhasePlan | None  # None: the plan's last phase is done
    step: int
    resume: bool  # a checkpoint to continue (else the phase starts)
    init: Path | None = None
    steps_left: int | None = None  # --lease-steps still to train
    process: subprocess.Popen | None = None
    started: float = 0.0
    segments: list[Segment] = field(default_factory=list)

    @property
    def folder(self) -> Path:
        return self.work / self.shape / f"p{self.phase.phase}"

    @property
    def newest(self) -> Path | None:
        """The checkpoint holding the run's newest state: this phase's, or the finished phase's before it."""
        if self.phase is not None and (self.folder / "last.pt").is_file():
            return self.folder / "last.pt"
        return self.init if self.init is not None and self.init.is_file() else None


def trainer_command(plan: CampaignPlan, course: Course, spool: Path, device: str, minutes: float,
                    threads: int | None, log_every: int) -> list[str]:
    phase = course.phase
    command = [sys.executable, "-m", "cuboidtrain", "run", "--phase", phase.phase, "--spool", str(spool),
               "--shape", course.shape, "--size", str(plan.size), "--arch", plan.arch, "--reframe",
               "--batch-size", str(plan.batch_size), "--lr", repr(phase.lr), "--lr-schedule", "cosine",
               "--steps", str(phase.steps), "--max-minutes", f"{max(minutes, 0.01):.3f}", "--max-wait", "120",
               "--loader-workers", str(plan.loader_workers), "--seed", str(plan.seed), "--device", device,
               "--checkpoint-every", str(CHECKPOINT_EVERY), "--log-every", str(log_every), "--no-dashboard",
               "--out", str(course.folder)]
    if plan.sigma is not None:
        command += ["--sigma", repr(plan.sigma)]
    if course.steps_left is not None:
        command += ["--stop-at", str(course.step + course.steps_left)]
    if threads is not None:
        command += ["--threads", str(threads)]
    if course.resume:
        return command + ["--resume"]
    return command + ["--overwrite"] + (["--init", str(course.init)] if course.init else [])


def train_until(plan: CampaignPlan, courses: list[Course], spools: dict[str, Path], device: str,
                deadline: float, threads: int | None = None, log_every: int = 10) -> list[Course]:
    """Every shape trained until `deadline` (monotonic s), its phase's steps, or its lease steps."""
    active = [c for c in courses if _start(plan, c, spools[c.shape], device, deadline, threads, log_every)]
    while active:
        time.sleep(0.2)
        for course in list(active):
            code = course.process.poll()
            if code is None:
                _hurry(course, deadline)
                continue
            _finish(plan, course, code)
            if not _start(plan, course, spools[course.shape], device, deadline, threads, log_every):
                active.remove(course)
    return courses


def _start(plan: CampaignPlan, course: Course, spool: Path, device: str, deadline: float,
           threads: int | None, log_every: int) -> bool:
    """Start the course's next trainer, if it has a phase to train, steps and time left, and its last did not fail."""
    left, last = deadline - time.monotonic(), course.segments[-1] if course.segments else None
    if course.phase is None or course.steps_left == 0:
        return False  # the plan's phases, or this lease's steps, are done
    if last is not None and (last.failed or left < LEAST_PHASE_S or last.to_step == last.from_step and last.phase == course.phase.phase):
        return False  # a trainer failed, too little time is left for another, or one ended without a step
    folder = course.folder
    folder.mkdir(parents=True, exist_ok=True)
    command = trainer_command(plan, course, spool, device, (left - STARTUP_S) / 60, threads, log_every)
    log.info("%s: phase %s from step %d to %d, at most %.1f min%s", course.shape, course.phase.phase, course.step,
             course.phase.steps, left / 60, "" if course.steps_left is None else f" or {course.steps_left} steps")
    course.process = subprocess.Popen(command, stdout=open(folder / "trainer.log", "a"), stderr=subprocess.STDOUT)
    course.started = time.monotonic()
    return True


def _hurry(course: Course, deadline: float) -> None:
    """A trainer past the deadline (a slow checkpoint, a hung loader) is asked to stop, then killed."""
    late = time.monotonic() - deadline
    if late > 2 * OVERRUN_S:
        course.process.kill()
    elif late > OVERRUN_S:
        course.process.terminate()


def _finish(plan: CampaignPlan, course: Course, code: int) -> None:
    """Account the trainer that ended, and move the course on: the next phase when this one is done."""
    folder = course.folder
    reached = _reached(folder, course.step)
    samples_per_s, wait = pace(folder / "metrics.jsonl", course.step)
    failed = None if code == 0 else f"exit {code}: {_last_line(folder / 'trainer.log')}"
    course.segments.append(Segment(course.phase.phase, course.step, reached, time.monotonic() - course.started,
                                   samples_per_s, wait, failed))
    if failed:
        log.warning("%s: phase %s trainer failed (%s)", course.shape, course.phase.phase, failed)
    if course.steps_left is not None:
        course.steps_left -= reached - course.step
    course.step, course.resume, course.process = reached, True, None
    if reached >= course.phase.steps:
        course.init, course.phase = folder / "last.pt", plan.phase_after(course.phase.phase)
        course.step, course.resume = 0, False


def _reached(folder: Path, before: int) -> int:
    """The step the run folder's checkpoint holds, as its status says (`before` if it says none)."""
    try:
        last = read_status(folder).last_checkpoint
    except (OSError, ValueError):  # no status.json yet, or a torn one
        return before
    return (last.step if last is not None else None) or before


def pace(metrics: Path, after: int) -> tuple[float | None, float | None]:
    """Samples/s and the data wait's share of step time over the records after step `after`,
    time-weighted (the first record after a start is left out: it holds the start-up)."""
    try:
        records = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    except OSError:
        return None, None
    timed = [r for r in records if r.get("step", 0) > after and "samples_per_s" in r and "time" in r]
    pairs = list(zip(timed, timed[1:]))
    weights = [b["time"] - a["time"] for a, b in pairs]
    if not pairs or sum(weights) <= 0:
        return None, None
    rate = sum(w * b["samples_per_s"] for w, (a, b) in zip(weights, pairs)) / sum(weights)
    wait = sum(w * b.get("data_wait_fraction", 0.0) for w, (a, b) in zip(weights, pairs)) / sum(weights)
    return rate, wait


def _last_line(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return "no log"
    return lines[-1][-300:] if lines else "no output"
