"""The training daemon: `run(config)` trains R, S and T from the rolling spool.

One loop, in labelled phases: fetch a batch (timed: that is the data wait),
render its targets on the device, forward/backward/step, account, report,
checkpoint, stop. SIGTERM and Ctrl-C finish the step in hand, write a
checkpoint and return.

Under torchrun every rank runs this loop on its share of each batch; the ranks
agree (cuboidtrain.train.distributed) on each batch's fate and on when to stop, and
only rank 0 writes.
"""
from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import signal
import time
from pathlib import Path

import torch

from cuboidtrain.models.checkpoint import load_checkpoint, non_finite_weights, save_checkpoint, set_rng_state
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.data import (FreshnessMeter, WaitInterrupted, loader_state, make_loader, prepare_batch, spool_names,
                                    workers_stopped)
from cuboidtrain.models.device import resolve_device
from cuboidtrain.train.distributed import Ranks, from_environment, shutdown, weights_digest, wrap
from cuboidtrain.train.files import drop_records_after, repair_jsonl, sweep_orphans
from shared.files import write_json
from cuboidtrain.train.losses import combine, phase_losses
from cuboidtrain.train.preflight import LAST, check_paths, least_batch
from cuboidtrain.models.networks import CuboidNet, build_model
from cuboidtrain.train.monitor.progress import Progress
from cuboidtrain.train.spoolwatch import SpoolCensus
from cuboidtrain.train.monitor.status import TrainingFailed
from shared.errors import UsageError

log = logging.getLogger(__name__)

IDLE_WAIT = (0.5, 30.0)  # s: first and longest pause between listings of a spool with no usable sample


class NoUsableSamples(TrainingFailed):
    """--max-wait ran out with nothing to train on: an empty spool, or none of its samples usable."""


class Diverged(UsageError):
    """A step gave a NaN or infinite loss, or left weights that are: the run stops before any
    record, status or checkpoint could hold them, and the last checkpoint stays the last finite one."""


def divergence(losses: dict[str, float], model: torch.nn.Module) -> str | None:
    """What is NaN or Infinity after a step, its losses or its weights; None when nothing is.
    One reduction over the weights (a NaN or Infinity anywhere makes the sum non-finite), one
    sync. Every rank finds the same: the losses are global_losses', the weights DDP's."""
    bad = [f"{name} is {value}" for name, value in losses.items() if not math.isfinite(value)]
    if bad:
        return ", ".join(bad)
    with torch.no_grad():
        tensors = [t for t in (*model.parameters(), *model.buffers()) if t.is_floating_point()]
        if math.isfinite(torch.stack([t.float().sum() for t in tensors]).sum().item()):
            return None
    count, total = non_finite_weights(model.state_dict())
    return f"{count} of {total} weights are NaN or Infinity after it"


def next_wait(wait: float) -> float:
    """The pause after `wait` while the spool stays unusable: doubled, at most IDLE_WAIT[1]."""
    return min(2 * wait, IDLE_WAIT[1])


def idle_pause(seconds: float, stop) -> None:
    """Sleep between listings, waking early when a stop is asked for."""
    deadline = time.monotonic() + seconds
    while not stop and time.monotonic() < deadline:
        time.sleep(min(0.1, max(deadline - time.monotonic(), 0)))


class StopRequest:
    """Set by SIGTERM or SIGINT; the loop checks it between steps.

    Python runs a signal's handler in the main thread, between bytecodes: not while that
    thread is inside a step's backward pass, which can take seconds. `asked` sees the
    signal at once, from any thread, through the wakeup file the signal module writes
    the signal's number to (installed() sets it up), so the dashboard can say
    "stopping after this step" while the step is still running."""

    STOPS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signal: int | None = None
        self._wakeup: int | None = None  # the read end of the signal module's wakeup pipe
        self._woken = False

    def __bool__(self) -> bool:
        return self.signal is not None

    def asked(self) -> bool:
        """Whether a stop was asked for, even one whose handler has not run yet."""
        if self.signal is not None or self._woken:
            return True
        if self._wakeup is not None:
            try:
                self._woken = any(b in self.STOPS for b in os.read(self._wakeup, 64))
            except (BlockingIOError, OSError):
                pass
        return self._woken

    @contextlib.contextmanager
    def installed(self):
        handler = lambda signum, frame: setattr(self, "signal", signum)  # noqa: E731
        previous = {s: signal.signal(s, handler) for s in self.STOPS}
        read, write = os.pipe()
        os.set_blocking(read, False)
        os.set_blocking(write, False)
        wakeup = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        self._wakeup = read
        try:
            yield self
        finally:
            signal.set_wakeup_fd(wakeup)
            self._wakeup = None
            os.close(read)
            os.close(write)
            for s, h in previous.items():
                signal.signal(s, h)


def _leave_signals_to_main(_worker_id: int) -> None:
    # Ctrl-C reaches the whole process group, and systemd or `pkill -f` send SIGTERM to
    # every process: the main process decides when to stop (after a checkpoint), so a
    # loader worker must not die under it. Workers exit on their own when main is gone.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def build_state(config: TrainConfig, device: torch.device) -> tuple[CuboidNet, torch.optim.Optimizer, int, dict | None]:
    """Model, optimizer, first step and a checkpoint to resume from (None for a fresh run)."""
    torch.manual_seed(config.seed)
    model = build_model(config.shape, config.size, config.seed, config.heatmap_sigma, config.arch)
    resume = None
    if config.resume:
        resume = load_checkpoint(Path(config.out) / LAST, config.shape, config.size, config.arch)
        if resume["config"]["phase"] != config.phase:
            raise UsageError(f"--resume: {config.out}/{LAST} is phase {resume['config']['phase']}, not {config.phase}")
        model.load_state_dict(resume["model"])
    elif config.init:
        model.load_state_dict(load_checkpoint(config.init, config.shape, config.size, config.arch)["model"])
    model.to(device)
    if device.type == "cuda":
        model.to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    if resume is not None:
        optimizer.load_state_dict(resume["optimizer"])
        set_rng_state(resume["rng"])
    return model, optimizer, (resume["step"] if resume else 0), resume


def train_step(model: CuboidNet, optimizer: torch.optim.Optimizer, x: dict, config: TrainConfig,
               device: torch.device, losses_of=None) -> dict[str, float]:
    """`losses_of`: the DDP module computing the phase's losses (torchrun), else None."""
    model.train()
    amp = config.amp and device.type == "cuda"
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
        if losses_of is not None:
            losses = losses_of(x)
        else:
            losses = phase_losses(model, x, config.phase, config.ratio_weight)
    total = combine(losses, config.phase, config.loss_weights)
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    return {"D_R": losses["D_R"].item(), "D_S": losses["D_S"].item(), "D_T": losses["D_T"].item(), "total": total.item()}


def stale(skipped: dict, batch_size: int) -> bool:
    """More than half of the (global) batch vanished: the epoch's listing no longer matches the spool."""
    return 2 * skipped["vanished"] > batch_size


def batch_facts(ranks: Ranks, batch: dict, least: int = 2) -> tuple[dict, bool]:
    """The batch's skip counts summed over ranks, and whether any rank holds fewer than `least`
    samples, too few to step on (`least_batch`): every rank then skips it, or DDP would hang."""
    if not ranks.distributed:
        return batch["skipped"], len(batch["names"]) < least
    sums = ranks.sum([*batch["skipped"].values(), float(len(batch["names"]) < least)])
    return dict(zip(batch["skipped"], (int(n) for n in sums))), sums[-1] > 0


def global_losses(ranks: Ranks, losses: dict[str, float], samples: int) -> tuple[dict[str, float], int]:
    """The losses averaged over ranks (the global batch's) and the samples all ranks stepped on."""
    if not ranks.distributed:
        return losses, samples
    sums = ranks.sum([*losses.values(), samples])
    return {k: v / ranks.world for k, v in zip(losses, sums)}, int(sums[-1])


def learning_rate(config: TrainConfig, step: int) -> float:
    """The rate for the step after `step`: constant, or cosine from lr down to lr/100 at --steps."""
    if config.lr_schedule == "constant":
        return config.lr
    progress = min(step / config.steps, 1.0)
    floor = config.lr / 100
    return floor + (config.lr - floor) * 0.5 * (1 + math.cos(math.pi * progress))


def finished(config: TrainConfig, step: int, epoch: int, started: float | None = None) -> bool:
    if config.max_minutes is not None and started is not None and time.monotonic() - started > config.max_minutes * 60:
        return True
    if config.steps is not None:
        return step >= config.steps
    return config.epochs is not None and epoch >= config.epochs


def run(config: TrainConfig, dashboard=None, stop: StopRequest | None = None, loader_timeout: float | None = None) -> dict:
    """Trains until --steps or --epochs are done or a stop is requested; returns the final status.

    Without a `stop` of the caller's, SIGTERM and Ctrl-C end the step in hand, then checkpoint.
    """
    with contextlib.ExitStack() as stack:
        if stop is None:
            stop = stack.enter_context(StopRequest().installed())
        return _train(config.validate(), dashboard, stop, loader_timeout)


def _train(config: TrainConfig, dashboard, stop: StopRequest, loader_timeout: float | None) -> dict:
    check_paths(config)
    ranks, device = from_environment(resolve_device(config.device))
    try:
        return _train_ranks(config, dashboard, stop, loader_timeout, ranks, device)
    finally:
        shutdown(ranks)


def _prepare_out(out: Path, config: TrainConfig) -> None:
    """The run folder, cleared of what a killed trainer left: temporary files, a torn last record."""
    out.mkdir(parents=True, exist_ok=True)
    swept = sweep_orphans(out)
    if swept:
        log.info("swept %d temporary files left in %s by a killed trainer", swept, out)
    repair_jsonl(out / "metrics.jsonl")
    write_json(out / "config.json", config.resolved().to_dict(), indent=2)


def _train_ranks(config: TrainConfig, dashboard, stop: StopRequest, loader_timeout: float | None,
                 ranks: Ranks, device: torch.device) -> dict:
    out = Path(config.out)
    if not ranks.main:
        logging.getLogger().setLevel(logging.WARNING)  # one rank speaks for the run
    if config.threads is not None:
        # On a shared CPU a second intra-op thread that gets descheduled stalls every
        # barrier of the other; fewer threads can be faster than all cores.
        torch.set_num_threads(config.threads)
    model, optimizer, step, resume = build_state(config, device)  # before OUT is touched: a bad --init changes nothing
    least = least_batch(model, device)
    if config.batch_size < least:
        raise UsageError(f"--batch-size {config.batch_size}: the {config.arch} arch at --size {config.size} needs at "
                         f"least {least} samples per step (BatchNorm over a 1x1 map)")
    kept = step if resume is not None else None  # the step OUT/last.pt holds, which a failure keeps
    if ranks.main:
        _prepare_out(out, config)
        if config.overwrite:  # asked to start over: no step of the old run is resumed after a crash
            (out / LAST).unlink(missing_ok=True)
        # steps after the start (a checkpoint, or 0) are trained again: record them once
        drop_records_after(out / "metrics.jsonl", step)
    losses_of = wrap(model, config.phase, config.ratio_weight, ranks)
    loader, sampler = make_loader(config.spool, config.shape, config.size, config.batch_size, config.seed,
                                  config.loader_workers, pin_memory=device.type == "cuda",
                                  timeout=loader_timeout if loader_timeout is not None else config.max_wait,
                                  worker_init_fn=_leave_signals_to_main, reframe="always" if config.reframe else "never",
                                  **_sampler_options(ranks, stop))
    if resume is not None and loader_state(resume) is not None:
        sampler.resume_from(loader_state(resume))
    freshness = FreshnessMeter()
    started, sigma, first_step = time.monotonic(), config.heatmap_sigma, step
    wait, idle_since = IDLE_WAIT[0], None  # the next pause between unusable listings; since when none was usable
    # The spool's count, arrival rate and evictions come from the listings the sampler makes
    # anyway: an inotify watcher's thread took the GIL for every publish (issue 14).
    census = SpoolCensus(config.spool)
    # On any failure the status says `failed` and the loader's workers are stopped (issue 22: a
    # full disk left "training" in status.json and a trainer hung on its workers).
    with Progress(config, device, census, dashboard, ranks.rank, ranks.world, stop=stop) as progress, \
            workers_stopped(loader):
        said = {"at": -math.inf, "total": 0}
        sampler.on_listing = lambda names: (_account_listing(census, names, ranks.main, said),
                                            freshness.forget_except(names),
                                            progress.listed(config.spool))
        progress.begin(step, sampler)
        while not ranks.any(bool(stop) or finished(config, step, sampler.epochs_done(), started)):
            progress.state("waiting for samples" if census.count < config.batch_size else "training")
            stepped = went_stale = False
            unusable = {}  # this listing's skipped samples, by reason
            try:
                for batch in loader:  # one epoch: the spool as listed now (this rank's share of it)
                    # 1. fetch: the time spent waiting for this batch is the data wait
                    waited = progress.fetched()
                    taken = sampler.advance()
                    skipped, too_small = batch_facts(ranks, batch, least)
                    # the names this global batch was meant to hold were read, but for those found gone (on this rank)
                    census.read(set(taken) - set(batch["vanished"]))
                    unusable = {k: unusable.get(k, 0) + n for k, n in skipped.items()}
                    if stale(skipped, config.batch_size * ranks.world):
                        # The generator evicted most of this listing (it outruns the trainer):
                        # end the epoch and list the spool afresh rather than skip through it.
                        progress.skip(skipped)
                        sampler.end_epoch()
                        went_stale = True
                        break
                    if too_small:  # fewer than `least` samples left: BatchNorm cannot step on them
                        progress.skip(skipped)
                        unusable["in_short_batches"] = unusable.get("in_short_batches", 0) + len(batch["names"])
                        continue
                    # 2. targets rendered on the device; forward, backward, step
                    x = prepare_batch(batch, device, sigma, config.size)
                    for group in optimizer.param_groups:
                        group["lr"] = learning_rate(config, step)
                    losses = train_step(model, optimizer, x, config, device, losses_of)
                    step += 1
                    stepped, wait, idle_since = True, IDLE_WAIT[0], None
                    # 3. account and report
                    age, reuse = freshness.observe(batch["names"])
                    losses, samples = global_losses(ranks, losses, len(batch["names"]))
                    if (fault := divergence(losses, model)) is not None:  # before any record could hold it
                        progress.state("failed")
                        raise Diverged(f"training diverged at step {step}: {fault}; stopped, "
                                       f"{_kept(progress, out, first_step if config.resume else None)} "
                                       f"(lower --lr, or look for bad samples: cuboidgen inspect {config.spool})")
                    progress.step(step, losses, samples, waited, age, reuse, skipped)
                    # 4. checkpoint, and validate when asked (rank 0; the others go on to the next collective)
                    if step % config.checkpoint_every == 0:
                        kept = _checkpoint(ranks, out, model, config, step, optimizer, sampler, progress, kept)
                    if ranks.main and config.val_spool and step % config.val_every == 0:
                        _validate(progress, model, config, device, step)
                    if ranks.any(bool(stop) or finished(config, step, sampler.epochs_done(), started)):
                        break
            except WaitInterrupted:
                break
            except TimeoutError as exc:  # --max-wait ran out while the spool held less than a batch
                progress.state("gave up")
                raise NoUsableSamples(f"{exc}; gave up (--max-wait {sampler.timeout:g})") from None
            if not (stepped or went_stale):
                # Every sample of the listing was unusable (corrupt, another shape or size, cut
                # off): wait before listing again, longer each time, rather than spin through
                # the same files; give up after --max-wait.
                idle_since = time.monotonic() if idle_since is None else idle_since
                reason = _unusable_reason(config, unusable)
                left = math.inf if config.max_wait is None else config.max_wait - (time.monotonic() - idle_since)
                if ranks.any(left <= 0):
                    progress.idle(reason, None)
                    progress.state("gave up")
                    raise NoUsableSamples(f"{reason}; gave up after {time.monotonic() - idle_since:.0f} s "
                                          f"(--max-wait {config.max_wait:g})")
                progress.idle(reason, min(wait, left))
                idle_pause(min(wait, left), stop)
                wait = next_wait(wait)
        # 5. the last checkpoint, also on SIGTERM / Ctrl-C; none before a step was trained
        if step > first_step:
            progress.state("checkpointing")
            kept = _checkpoint(ranks, out, model, config, step, optimizer, sampler, progress, kept)
        if ranks.distributed:
            progress.replicas(ranks.gather({"rank": ranks.rank, "step": step, "weights": weights_digest(model)}))
        progress.state("stopped" if ranks.any(bool(stop)) else "done")
        return progress.status()


EVICTED_LOG_EVERY = 60.0  # s between warnings about samples evicted unread (a fast generator makes short epochs)


def _account_listing(census: SpoolCensus, names: list[str], speaks: bool, said: dict) -> None:
    """An epoch's listing: the census counts what was evicted unread since the last one, and
    the log says so, at most once a minute (`said`: when it last did, and the total then)."""
    census.listed(names)
    total, unread = census.evicted_unread_total, census.evicted_unread
    if speaks and total > said["total"] and time.monotonic() - said["at"] >= EVICTED_LOG_EVERY:
        log.warning("%d samples evicted before the trainer read them since the last warning, %d in all (%d never "
                    "listed, %d listed but never read): the generator outruns the trainer (cuboidgen run --max-rate)",
                    total - said["total"], total, unread["never_listed"], unread["listed_unread"])
        said.update(at=time.monotonic(), total=total)


def _unusable_reason(config: TrainConfig, skipped: dict) -> str:
    """Why the last listing gave nothing to train on, with what would fix it."""
    counts = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in skipped.items() if n) or "none read"
    reason = f"spool {config.spool}: no usable sample in the last listing ({counts})"
    if skipped.get("other_size"):
        reason += f"; samples of another size need --reframe, or a generator with --size {config.size}"
    elif skipped.get("other_shape"):
        reason += f"; the spool holds no {config.shape} samples (--shape)"
    return reason


def _kept(progress: Progress, out: Path, resumed: int | None) -> str:
    """What the run folder holds for a run that stops now: its last checkpoint, or none."""
    last = progress.status()["last_checkpoint"]
    step = last["step"] if last else resumed
    return f"{out / LAST} keeps step {step}" if step is not None else "no checkpoint was written"


def _sampler_options(ranks: Ranks, stop: StopRequest) -> dict:
    """Under torchrun: this rank's share, rank 0's listing, and a stop any rank asks for."""
    if not ranks.distributed:
        return {"interrupted": lambda: bool(stop)}
    return {"rank": ranks.rank, "world": ranks.world, "interrupted": lambda: ranks.any(bool(stop)),
            "list_spool": lambda spool: ranks.broadcast(spool_names(spool) if ranks.main else None)}


def _checkpoint(ranks: Ranks, out: Path, model: CuboidNet, config: TrainConfig, step: int, optimizer, sampler,
                progress: Progress, kept: int | None) -> int:
    """Rank 0 writes OUT/last.pt (the unwrapped model: no `module.` prefix); returns the step it
    holds now. `kept`: the step it held before, which a failed write leaves in place."""
    path = out / LAST
    if ranks.main:
        try:
            save_checkpoint(path, model, config, step, optimizer, sampler.snapshot(), progress.metrics())
        except OSError as exc:  # the temporary file is closed and removed: the disk has its space back
            what = (f"out of space writing {path} at step {step}" if exc.errno in (errno.ENOSPC, errno.EDQUOT)
                    else f"cannot write {path} at step {step} ({exc.strerror or exc})")
            then = (f"kept the step-{kept} checkpoint (--resume continues it)" if kept is not None
                    else "no earlier checkpoint to keep")
            raise TrainingFailed(f"{what}: {then}") from None
    progress.checkpointed(path, step)
    return step


def _validate(progress: Progress, model: CuboidNet, config: TrainConfig, device: torch.device, step: int) -> None:
    """Validation at `step`. A validation spool gone bad since start-up (emptied, removed) costs
    no step: the status and the log say so, and training goes on."""
    try:
        progress.validated(step, validate(model, config, device))
    except (UsageError, OSError) as exc:
        progress.validation_failed(f"--val-spool {config.val_spool}: validation at step {step} failed ({exc}); "
                                   f"training goes on")


def validate(model: CuboidNet, config: TrainConfig, device: torch.device) -> dict:
    from cuboidtrain.train.evaluate import evaluate  # evaluation pulls in nothing the loop needs otherwise
    from cuboidtrain.fit.options import FitOptions

    return evaluate(model, Path(config.val_spool), config.heatmap_sigma, FitOptions(device=device),
                    max_samples=config.val_samples)
