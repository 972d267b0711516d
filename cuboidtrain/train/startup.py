"""A training run's start-up: the model and optimizer built or resumed, the run folder made ready, the spool's loader opened."""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from cuboidtrain.allocator import keep_freed_memory
from cuboidtrain.models.checkpoint import DamagedFile, load_checkpoint, set_rng_state
from cuboidtrain.models.networks import CuboidNet, build_model
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.loader import make_loader
from cuboidtrain.data.sampler import EpochSampler, loader_state, spool_names
from cuboidtrain.train.distributed import Ranks, wrap
from cuboidtrain.train.run_files import drop_records_after, repair_jsonl, sweep_orphans
from cuboidtrain.train.preflight import LAST, PREVIOUS, least_batch
from cuboidtrain.train.stop_and_wait import StopRequest, leave_signals_to_main
from shared.errors import UsageError
from shared.files import write_json

log = logging.getLogger(__name__)
# On a CPU every batch allocates the same large buffers (the heat maps: 32 MB at 64 px): up to this
# many bytes come from the heap and stay there for the next batch rather than being faulted in again
# (`cuboidtrain.allocator`; the loader's workers, forked after, inherit it). On a GPU they live there.
TRAINER_KEEPS = 1 << 30


@dataclass(frozen=True)
class Start:
    """The model and optimizer a run starts from, the step they are at, and the checkpoint
    resumed (None for a fresh run)."""

    model: CuboidNet
    optimizer: torch.optim.Optimizer
    step: int
    resume: dict | None


@dataclass(frozen=True)
class Setup:
    """What start-up hands the loop: the model, its optimizer and (under torchrun) the DDP module
    computing its losses, the loader and its sampler, the least batch BatchNorm can step on,
    the step training starts after, and the step OUT/last.pt holds (None: none yet)."""

    model: CuboidNet
    optimizer: torch.optim.Optimizer
    losses_of: torch.nn.Module | None
    loader: DataLoader
    sampler: EpochSampler
    least: int
    step: int
    kept: int | None


def resumable(config: TrainConfig) -> dict:
    """The checkpoint `--resume` continues: OUT/last.pt, or where its bytes are damaged (a flipped
    bit, a torn copy) the one before it, OUT/previous.pt, saying so; DamagedFile when both are."""
    last, previous = Path(config.out) / LAST, Path(config.out) / PREVIOUS
    try:
        return load_checkpoint(last, config.shape, config.size, config.arch)
    except DamagedFile as damaged:
        if not previous.is_file():
            raise DamagedFile(f"{damaged}, and there is no {PREVIOUS} to fall back to") from None
        resume = load_checkpoint(previous, config.shape, config.size, config.arch)
        # set aside, not deleted (to look at), and never linked as the next previous.pt
        os.replace(last, last.with_name(LAST + ".damaged"))
        log.warning("%s; resuming from %s (step %d) instead; the damaged file is now %s.damaged",
                    damaged, previous, resume["step"], LAST)
        return resume


def build_state(config: TrainConfig, device: torch.device) -> Start:
    """Model, optimizer, first step and a checkpoint to resume from (None for a fresh run)."""
    torch.manual_seed(config.seed)
    model = build_model(config.shape, config.size, config.seed, config.heatmap_sigma, config.arch, config.grey_input)
    resume = None
    if config.resume:
        resume = resumable(config)
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
    return Start(model, optimizer, (resume["step"] if resume else 0), resume)


def set_up(config: TrainConfig, ranks: Ranks, device: torch.device, stop: StopRequest,
           loader_timeout: float | None) -> Setup:
    """Everything before the first step, in this order: the model (before OUT is touched: a bad
    --init changes nothing), the batch size checked against it, the run folder, the loader."""
    if not ranks.main:
        logging.getLogger().setLevel(logging.WARNING)  # one rank speaks for the run
    if config.threads is not None:
        # On a shared CPU a second intra-op thread that gets descheduled stalls every
        # barrier of the other; fewer threads can be faster than all cores.
        torch.set_num_threads(config.threads)
    if device.type == "cpu" and not keep_freed_memory(TRAINER_KEEPS, TRAINER_KEEPS):
        log.debug("glibc's allocator not tuned (not glibc): each batch's buffers are mapped afresh")
    start = build_state(config, device)
    least = least_batch(start.model, device)
    if config.batch_size < least:
        raise UsageError(f"--batch-size {config.batch_size}: the {config.arch} arch at --size {config.size} needs at "
                         f"least {least} samples per step (BatchNorm over a 1x1 map)")
    if ranks.main:
        prepare_out(config, start.step)
    losses_of = wrap(start.model, config.phase, config.ratio_weight, ranks)
    loader, sampler = open_loader(config, ranks, device, stop, loader_timeout)
    if start.resume is not None and loader_state(start.resume) is not None:
        sampler.resume_from(loader_state(start.resume))
    return Setup(start.model, start.optimizer, losses_of, loader, sampler, least, start.step,
                 start.step if start.resume is not None else None)


def prepare_out(config: TrainConfig, step: int) -> None:
    """The run folder, cleared of what a killed trainer left (temporary files, a torn last record)
    and of the records after `step`, which are trained again; with --overwrite, of its last.pt."""
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    swept = sweep_orphans(out)
    if swept:
        log.info("swept %d temporary files left in %s by a killed trainer", swept, out)
    repair_jsonl(out / "metrics.jsonl")
    for ledger in out.glob("ledger*.jsonl"):  # --ledger's, whether or not this run keeps one
        repair_jsonl(ledger)
    write_json(out / "config.json", config.resolved().to_dict(), indent=2)
    if config.overwrite:  # asked to start over: no step of the old run is resumed after a crash
        (out / LAST).unlink(missing_ok=True)
        (out / PREVIOUS).unlink(missing_ok=True)
    # steps after the start (a checkpoint, or 0) are trained again: record them once
    drop_records_after(out / "metrics.jsonl", step)


def open_loader(config: TrainConfig, ranks: Ranks, device: torch.device, stop: StopRequest,
                loader_timeout: float | None) -> tuple[DataLoader, EpochSampler]:
    """The spool's loader and its sampler (`make_loader`'s), this rank's share under torchrun."""
    return make_loader(config.spool, config.shape, config.size, config.batch_size, config.seed,
                       config.workers_on(device.type), pin_memory=device.type == "cuda",
                       timeout=loader_timeout if loader_timeout is not None else config.max_wait,
                       worker_init_fn=leave_signals_to_main, reframe="always" if config.reframe else "never",
                       **_sampler_options(ranks, stop))


def _sampler_options(ranks: Ranks, stop: StopRequest) -> dict:
    """Under torchrun: this rank's share, rank 0's listing, and a stop any rank asks for."""
    if not ranks.distributed:
        return {"interrupted": lambda: bool(stop)}
    return {"rank": ranks.rank, "world": ranks.world, "interrupted": lambda: ranks.any(bool(stop)),
            "list_spool": lambda spool: ranks.broadcast(spool_names(spool) if ranks.main else None)}
