"""The training daemon: `run(config)` trains R, S and T from the rolling spool.

One loop, in phases of their own: start-up (cuboidtrain.train.startup), then epoch after epoch
(`train_epochs`, `train_one_epoch`), each step a phase (`train_one_step`: the batch's targets
rendered on the device, forward/backward/step, account, report) followed by its checkpoint and
validation (`after_step`); a spool with nothing usable is waited on (`wait_for_usable`), and the
run ends with its last checkpoint (`shut_down`). SIGTERM and Ctrl-C finish the step in hand,
write a checkpoint and return. Between the phases go frozen results: `Position`, `Epoch`,
`BatchFacts` and `StepLosses` (cuboidtrain.train.agreement), and the final `TrainerStatus`.

Under torchrun every rank runs this loop on its share of each batch; the ranks
agree (cuboidtrain.train.agreement) on each batch's fate and on when to stop, and
only rank 0 writes.
"""
from __future__ import annotations

import contextlib
import errno
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from cuboidtrain.data.census import SpoolCensus
from cuboidtrain.data.freshness import FreshnessMeter
from cuboidtrain.data.loader import LoaderBatch, workers_stopped
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.data.sampler import WaitInterrupted
from cuboidtrain.models.checkpoint import save_checkpoint
from cuboidtrain.models.device import resolve_device
from cuboidtrain.models.networks import CuboidNet
from cuboidtrain.train.agreement import BatchFacts, batch_facts, divergence, global_losses, stale
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.distributed import Ranks, from_environment, shutdown, weights_digest
from cuboidtrain.train.ledger import Ledger
from cuboidtrain.train.losses import combine, phase_losses
from cuboidtrain.train.monitor.progress import Progress
from cuboidtrain.train.monitor.status import Checkpoint, TrainerStatus, TrainingFailed
from cuboidtrain.train.preflight import LAST, PREVIOUS, check_paths
from cuboidtrain.train.startup import Setup, set_up
from cuboidtrain.train.stop_and_wait import Backoff, StopRequest, finished, idle_pause, unusable_reason
from shared.errors import UsageError

if TYPE_CHECKING:  # evaluation is imported when a validation runs: it pulls in nothing the loop needs otherwise
    from cuboidtrain.train.evaluate import Evaluation

log = logging.getLogger(__name__)

EVICTED_LOG_EVERY = 60.0  # s between warnings about samples evicted unread (a fast generator makes short epochs)


class NoUsableSamples(TrainingFailed):
    """--max-wait ran out with nothing to train on: an empty spool, or none of its samples usable."""


class Diverged(UsageError):
    """A step gave a NaN or infinite loss, or left weights that are: the run stops before any
    record, status or checkpoint could hold them, and the last checkpoint stays the last finite one."""


@dataclass(frozen=True)
class Position:
    """Where a run stands between steps: the last step trained, and the step OUT/last.pt holds
    (None: no checkpoint yet), which a failed write keeps."""

    step: int
    kept: int | None


@dataclass(frozen=True)
class Epoch:
    """What one epoch did: where it left the run, whether it trained a step, whether its listing
    went stale, its skipped samples by reason, and whether a stop cut its wait for samples short."""

    position: Position
    stepped: bool = False
    went_stale: bool = False
    unusable: dict[str, int] = field(default_factory=dict)
    interrupted: bool = False


@dataclass(frozen=True)
class Session:
    """What every phase of one run reads and none replaces: the options, the ranks, the device,
    the stop request, start-up's model and loader, the reporter and the spool's census."""

    config: TrainConfig
    ranks: Ranks
    device: torch.device
    stop: StopRequest
    setup: Setup
    progress: Progress
    census: SpoolCensus
    freshness: FreshnessMeter
    started: float  # monotonic s
    ledger: Ledger | None  # --ledger: each step's samples

    @property
    def out(self) -> Path:
        return Path(self.config.out)

    def done(self, step: int) -> bool:
        """Whether the run ends after `step`: a stop asked for, or the run finished, on any rank."""
        return self.ranks.any(bool(self.stop) or finished(self.config, step, self.setup.sampler.epochs_done(),
                                                          self.started))


@dataclass
class EvictionWarnings:
    """When the log last warned of samples evicted unread (monotonic s), and their total then."""

    at: float = -math.inf
    total: int = 0


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


def learning_rate(config: TrainConfig, step: int, elapsed_s: float = 0.0) -> float:
    """The rate for the step after `step`: constant, or cosine from lr down to lr/100 at --steps,
    or, without --steps, at --max-minutes of this run's wall time (`elapsed_s`): a lease of a
    GPU is counted in minutes, and how many steps fit in them is only known on the machine.
    Over minutes the rates follow the machine's pace, so two runs of one seed differ."""
    if config.lr_schedule == "constant":
        return config.lr
    if config.steps is not None:
        progress = min(step / config.steps, 1.0)
    else:
        progress = min(elapsed_s / (config.max_minutes * 60), 1.0)
    floor = config.lr / 100
    return floor + (config.lr - floor) * 0.5 * (1 + math.cos(math.pi * progress))


def schedule_seconds(config: TrainConfig, ranks, started: float) -> float:
    """This run's seconds so far for a schedule over --max-minutes: rank 0's on every rank, since
    DDP averages gradients, not weights, and replicas stepped at other rates would drift apart.
    0 where the schedule does not read the clock (no collective then)."""
    if config.lr_schedule != "cosine" or config.steps is not None:
        return 0.0
    elapsed = time.monotonic() - started
    return ranks.sum([elapsed if ranks.main else 0.0])[0] if ranks.distributed else elapsed


def run(config: TrainConfig, dashboard=None, stop: StopRequest | None = None,
        loader_timeout: float | None = None) -> TrainerStatus:
    """Trains until --steps or --epochs are done or a stop is requested; returns the final status.

    Without a `stop` of the caller's, SIGTERM and Ctrl-C end the step in hand, then checkpoint.
    """
    with contextlib.ExitStack() as stack:
        if stop is None:
            stop = stack.enter_context(StopRequest().installed())
        return _train(config.validate(), dashboard, stop, loader_timeout)


def _train(config: TrainConfig, dashboard, stop: StopRequest, loader_timeout: float | None) -> TrainerStatus:
    check_paths(config)
    ranks, device = from_environment(resolve_device(config.device))
    together = False
    try:
        status = _train_ranks(config, dashboard, stop, loader_timeout, ranks, device)
        together = status.state in ("done", "stopped")  # every rank agreed on it (`ranks.any`): all are here
        return status
    finally:
        shutdown(ranks, together=together)


def _train_ranks(config: TrainConfig, dashboard, stop: StopRequest, loader_timeout: float | None,
                 ranks: Ranks, device: torch.device) -> TrainerStatus:
    """Start-up, the epochs, the end. On any failure the status says `failed` and the loader's
    workers are stopped (issue 22: a full disk left "training" in status.json and a trainer
    hung on its workers)."""
    setup = set_up(config, ranks, device, stop, loader_timeout)
    freshness = FreshnessMeter()
    started = time.monotonic()
    # The spool's count, arrival rate and evictions come from the listings the sampler makes
    # anyway: an inotify watcher's thread took the GIL for every publish (issue 14).
    census = SpoolCensus(config.spool)
    ledger = Ledger.in_folder(Path(config.out), ranks.rank) if config.ledger else None
    with Progress(config, device, census, dashboard, ranks.rank, ranks.world, stop=stop) as progress, \
            workers_stopped(setup.loader), contextlib.closing(ledger) if ledger else contextlib.nullcontext():
        session = Session(config, ranks, device, stop, setup, progress, census, freshness, started, ledger)
        _listen(session)
        progress.begin(setup.step, setup.sampler, resumed_checkpoint(Path(config.out), setup.kept))
        position = train_epochs(session, Position(setup.step, setup.kept))
        return shut_down(session, position)


def train_epochs(s: Session, position: Position) -> Position:
    """Epoch after epoch until the run is done or stopped; after a listing with nothing usable,
    a wait that backs off."""
    backoff = Backoff()
    while not s.done(position.step):
        s.progress.state("waiting for samples" if s.census.count < s.config.batch_size else "training")
        epoch = train_one_epoch(s, position)
        position = epoch.position
        if epoch.interrupted:
            break
        if epoch.stepped:
            backoff = Backoff()
        elif not epoch.went_stale:
            backoff = wait_for_usable(s, epoch.unusable, backoff)
    return position


def train_one_epoch(s: Session, position: Position) -> Epoch:
    """The spool as listed now (this rank's share of it), batch by batch, until the epoch ends, its
    listing goes stale or the run is done. --max-wait running out while the spool holds less than
    a batch raises NoUsableSamples."""
    stepped, unusable = False, {}  # this listing's skipped samples, by reason
    try:
        for batch in s.setup.loader:
            # 1. fetch: the time spent waiting for this batch is the data wait
            waited = s.progress.fetched()
            facts = _taken(s, batch)
            unusable = {k: unusable.get(k, 0) + n for k, n in facts.skipped.items()}
            if stale(facts.skipped, s.config.batch_size * s.ranks.world):
                # The generator evicted most of this listing (it outruns the trainer):
                # end the epoch and list the spool afresh rather than skip through it.
                s.progress.skip(facts.skipped)
                s.setup.sampler.end_epoch()
                return Epoch(position, stepped, went_stale=True, unusable=unusable)
            if facts.too_small:  # fewer than `least` samples left: BatchNorm cannot step on them
                s.progress.skip(facts.skipped)
                unusable["in_short_batches"] = unusable.get("in_short_batches", 0) + len(batch.names)
                continue
            position = after_step(s, train_one_step(s, position, batch, waited, facts.skipped))
            stepped = True
            if s.done(position.step):
                break
    except WaitInterrupted:
        return Epoch(position, stepped, unusable=unusable, interrupted=True)
    except TimeoutError as exc:  # --max-wait ran out while the spool held less than a batch
        s.progress.state("gave up")
        raise NoUsableSamples(f"{exc}; gave up (--max-wait {s.setup.sampler.timeout:g})") from None
    return Epoch(position, stepped, unusable=unusable)


def _taken(s: Session, batch: LoaderBatch) -> BatchFacts:
    """A fetched batch taken: the sampler moves on, the ranks agree on its skips, the census counts it read."""
    taken = s.setup.sampler.advance()
    facts = batch_facts(s.ranks, batch, s.setup.least)
    # the names this global batch was meant to hold were read, but for those found gone (on this rank)
    s.census.read(set(taken) - set(batch.vanished))
    return facts


def train_one_step(s: Session, position: Position, batch: LoaderBatch, waited: float, skipped: dict) -> Position:
    """One step on `batch`, accounted and reported; a NaN or Infinity in its losses or the weights
    stops the run (Diverged) before any record, status or checkpoint could hold it."""
    config, setup = s.config, s.setup
    # 2. targets rendered on the device; forward, backward, step
    x = prepare_batch(batch, s.device, config.heatmap_sigma, config.size, config.grey_input)
    for group in setup.optimizer.param_groups:
        group["lr"] = learning_rate(config, position.step, schedule_seconds(config, s.ranks, s.started))
    losses = train_step(setup.model, setup.optimizer, x, config, s.device, setup.losses_of)
    step = position.step + 1
    if s.ledger is not None:
        s.ledger.record(step, batch.names, batch.checksums)
    # 3. account and report
    age, reuse = s.freshness.observe(batch.names)
    result = global_losses(s.ranks, losses, len(batch.names))
    if (fault := divergence(result.losses, setup.model)) is not None:
        s.progress.state("failed")
        raise Diverged(f"training diverged at step {step}: {fault}; stopped, "
                       f"{_kept(s.progress, s.out, setup.step if config.resume else None)} "
                       f"(lower --lr, or look for bad samples: cuboidgen inspect {config.spool})")
    s.progress.step(step, result.losses, result.samples, waited, age, reuse, skipped)
    return Position(step, position.kept)


def after_step(s: Session, position: Position) -> Position:
    """4. Checkpoint every --checkpoint-every steps, and validate every --val-every (rank 0; the
    others go on to the next collective)."""
    step, kept = position.step, position.kept
    if step % s.config.checkpoint_every == 0:
        kept = _checkpoint(s, step, kept)
    if s.ranks.main and s.config.val_spool and step % s.config.val_every == 0:
        _validate(s.progress, s.setup.model, s.config, s.device, step)
    return Position(step, kept)


def wait_for_usable(s: Session, unusable: dict, backoff: Backoff) -> Backoff:
    """Every sample of the listing was unusable (corrupt, another shape or size, cut off): wait
    before listing again, longer each time, rather than spin through the same files; give up
    (NoUsableSamples) after --max-wait."""
    config = s.config
    idle_since = time.monotonic() if backoff.idle_since is None else backoff.idle_since
    reason = unusable_reason(config, unusable)
    left = math.inf if config.max_wait is None else config.max_wait - (time.monotonic() - idle_since)
    if s.ranks.any(left <= 0):
        s.progress.idle(reason, None)
        s.progress.state("gave up")
        raise NoUsableSamples(f"{reason}; gave up after {time.monotonic() - idle_since:.0f} s "
                              f"(--max-wait {config.max_wait:g})")
    s.progress.idle(reason, min(backoff.wait, left))
    idle_pause(min(backoff.wait, left), s.stop)
    return backoff.after(idle_since)


def shut_down(s: Session, position: Position) -> TrainerStatus:
    """5. The last checkpoint, also on SIGTERM / Ctrl-C (none before a step was trained), each
    rank's final step and weights under torchrun, and the final status."""
    if position.step > s.setup.step:
        s.progress.state("checkpointing")
        _checkpoint(s, position.step, position.kept)
    if s.ranks.distributed:
        s.progress.replicas(s.ranks.gather({"rank": s.ranks.rank, "step": position.step,
                                            "weights": weights_digest(s.setup.model)}))
    s.progress.state("stopped" if s.ranks.any(bool(s.stop)) else "done")
    return s.progress.snapshot()


def _listen(s: Session) -> None:
    """Each epoch's listing: the census counts it, the freshness meter forgets the names gone,
    the reporter counts what else lies in the spool."""
    said = EvictionWarnings()
    s.setup.sampler.on_listing = lambda names: (account_listing(s.census, names, s.ranks.main, said),
                                                s.freshness.forget_except(names),
                                                s.progress.listed(s.config.spool))


def account_listing(census: SpoolCensus, names: list[str], speaks: bool, said: EvictionWarnings) -> None:
    """An epoch's listing: the census counts what was evicted unread since the last one, and
    the log says so, at most once a minute (`said`: when it last did, and the total then)."""
    census.listed(names)
    total, unread = census.evicted_unread_total, census.evicted_unread
    if speaks and total > said.total and time.monotonic() - said.at >= EVICTED_LOG_EVERY:
        log.warning("%d samples evicted before the trainer read them since the last warning, %d in all (%d never "
                    "listed, %d listed but never read): the generator outruns the trainer (cuboidgen run --max-rate)",
                    total - said.total, total, unread["never_listed"], unread["listed_unread"])
        said.at, said.total = time.monotonic(), total


def resumed_checkpoint(out: Path, step: int | None) -> Checkpoint | None:
    """The checkpoint a resumed run continues (step `step`; None: a fresh run): OUT/last.pt, or
    OUT/previous.pt where a damaged last.pt was set aside (`startup.resumable`), dated by its file."""
    if step is None:
        return None
    path = next((p for p in (out / LAST, out / PREVIOUS) if p.is_file()), out / LAST)
    return Checkpoint(str(path), step, path.stat().st_mtime if path.is_file() else None)


def _kept(progress: Progress, out: Path, resumed: int | None) -> str:
    """What the run folder holds for a run that stops now: its last checkpoint, or none."""
    last = progress.snapshot().last_checkpoint
    step = last.step if last else resumed
    return f"{out / LAST} keeps step {step}" if step is not None else "no checkpoint was written"


def _checkpoint(s: Session, step: int, kept: int | None) -> int:
    """Rank 0 writes OUT/last.pt (the unwrapped model: no `module.` prefix); returns the step it
    holds now. `kept`: the step it held before, which a failed write leaves in place."""
    path = s.out / LAST
    if s.ranks.main:
        try:
            save_checkpoint(path, s.setup.model, s.config, step, s.setup.optimizer, s.setup.sampler.snapshot(),
                            s.progress.metrics(), previous=s.out / PREVIOUS if kept != step else None)
        except OSError as exc:  # the temporary file is closed and removed: the disk has its space back
            what = (f"out of space writing {path} at step {step}" if exc.errno in (errno.ENOSPC, errno.EDQUOT)
                    else f"cannot write {path} at step {step} ({exc.strerror or exc})")
            then = (f"kept the step-{kept} checkpoint (--resume continues it)" if kept is not None
                    else "no earlier checkpoint to keep")
            raise TrainingFailed(f"{what}: {then}") from None
    s.progress.checkpointed(path, step)
    return step


def _validate(progress: Progress, model: CuboidNet, config: TrainConfig, device: torch.device, step: int) -> None:
    """Validation at `step`. A validation spool gone bad since start-up (emptied, removed) costs
    no step: the status and the log say so, and training goes on."""
    try:
        progress.validated(step, validate(model, config, device))
    except (UsageError, OSError) as exc:
        progress.validation_failed(f"--val-spool {config.val_spool}: validation at step {step} failed ({exc}); "
                                   f"training goes on")


def validate(model: CuboidNet, config: TrainConfig, device: torch.device) -> Evaluation:
    from cuboidtrain.train.evaluate import evaluate  # evaluation pulls in nothing the loop needs otherwise
    from cuboidtrain.fit.options import FitOptions

    return evaluate(model, Path(config.val_spool), config.heatmap_sigma, FitOptions(device=device),
                    max_samples=config.val_samples)
