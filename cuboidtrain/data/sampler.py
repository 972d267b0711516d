"""The epoch's order: the spool is enumerated afresh at every epoch (paper 3.3.2).

The sampler runs in the main process. At each epoch's start it lists the spool,
shuffles the names with a seed derived from (run seed, epoch) and yields
batches of names; the loader's workers read them (`cuboidtrain.data.loader`).
So the loader's state is just (epoch, order, position): a checkpoint stores it
and `--resume` continues with the very next batch. Only the sampler moves that
state; the trainer tells it what it did (`advance`, `end_epoch`) and asks where it
stands (`where`, `snapshot`).

Under torchrun each rank takes its strided share of every global batch (`rank_batches`);
the state (epoch, order, position) is the same on every rank, so one checkpoint resumes them all.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from torch.utils.data import Sampler

from shared.spool import enumerate_spool

log = logging.getLogger(__name__)


@dataclass
class LoaderState:
    """Where the loader stands: the current epoch's order and the next batch to train on."""

    epoch: int = 0
    order: list[str] = field(default_factory=list)
    position: int = 0  # batches of `order` already trained on (global batches: batch size x world)
    world: int = 1  # ranks that shared each batch (torchrun); a resume with another world rescales position


def loader_state(ckpt: dict) -> LoaderState | None:
    """The loader's position a checkpoint kept (`save_checkpoint(..., loader=)`), if it kept one."""
    return LoaderState(**ckpt["loader"]) if ckpt.get("loader") else None


@dataclass(frozen=True, slots=True)
class EpochPosition:
    """Where the loader stands, as the status shows it: the epoch, its batches taken and in all."""

    epoch: int
    taken: int  # global batches of this epoch already trained on (LoaderState.position)
    batches: int  # global batches in this epoch (len(EpochSampler))


class WaitInterrupted(Exception):
    """A stop was asked for while the sampler waited for samples."""


class EpochSampler(Sampler):
    """Yields the batches of one epoch per `iter()`: the spool as listed at the epoch's start.

    Waits (polling) while the spool holds fewer than one batch, so a trainer can
    start before its generator. Under torchrun (`world` > 1) it yields this rank's
    share of each global batch, and `list_spool` must give every rank the same names
    (rank 0's listing, broadcast); `interrupted` (agreed by all ranks) ends a wait.
    """

    def __init__(self, spool: str | Path, batch_size: int, seed: int, wait: float = 0.5, timeout: float | None = None,
                 rank: int = 0, world: int = 1, list_spool=None, interrupted=None):
        self.spool, self.batch_size, self.seed = Path(spool), batch_size, seed
        self.wait, self.timeout = wait, timeout
        self.rank, self.world = rank, world
        self.list_spool = list_spool or spool_names
        self.interrupted = interrupted  # () -> bool, polled while waiting for samples
        # Only the sampler moves its state: the trainer says what it did (advance, end_epoch)
        # and reads where it stands (where, snapshot).
        self._state = LoaderState(world=world)
        self.on_listing = None  # called with each epoch's listing (the trainer's freshness and spool count)
        self._resume = False  # True: the next iter() continues `_state` instead of starting a new epoch

    def resume_from(self, state: LoaderState) -> None:
        if state.world != self.world:  # the same samples consumed, counted in this world's global batches
            log.warning("resuming a %d-rank run on %d ranks: position %d rescaled", state.world, self.world, state.position)
            state = LoaderState(state.epoch, state.order, state.position * state.world // self.world, self.world)
        self._state, self._resume = state, True

    def advance(self) -> list[str]:
        """The trainer took the next global batch: moves past it and returns the names that batch
        was meant to hold (every rank's share, those found gone or unusable included)."""
        s, span = self._state, self.batch_size * self.world
        s.position += 1
        return s.order[(s.position - 1) * span : s.position * span]

    def end_epoch(self) -> None:
        """Counts the epoch as trained to its end (a stale listing): the next iter() lists the spool afresh."""
        self._state.position = len(self)

    def where(self) -> EpochPosition:
        """The epoch and how far into it the trainer is."""
        return EpochPosition(self._state.epoch, self._state.position, len(self))

    def snapshot(self) -> LoaderState:
        """The state a checkpoint stores (a copy: the sampler moves on)."""
        return replace(self._state, order=list(self._state.order))

    def __iter__(self):
        if not self._resume:
            epoch = self._state.epoch + 1 if self._state.order else 0
            self._state = LoaderState(epoch, self._shuffled(epoch), 0, self.world)
        self._resume = False
        state = self._state
        if self.world == 1:
            for start in range(state.position * self.batch_size, len(state.order) - self.batch_size + 1, self.batch_size):
                yield state.order[start : start + self.batch_size]
        else:
            yield from rank_batches(state.order, self.batch_size, self.rank, self.world, state.position)

    def __len__(self) -> int:
        return len(self._state.order) // (self.batch_size * self.world)

    def epochs_done(self) -> int:
        """Epochs trained to their end: the current one counts once its last batch is taken."""
        s = self._state
        return s.epoch + (1 if s.order and s.position >= len(self) else 0)

    def _shuffled(self, epoch: int) -> list[str]:
        names = self._listing()
        rng = np.random.default_rng([self.seed, epoch])
        return [names[i] for i in rng.permutation(len(names))]

    def _listing(self) -> list[str]:
        started, said = time.monotonic(), None
        need = self.batch_size * self.world
        while True:
            names = self.list_spool(self.spool)
            if len(names) >= need:
                if self.on_listing is not None:
                    self.on_listing(names)
                return names
            if said != len(names):  # once per change, not once per poll
                log.info("spool %s holds %d samples: waiting for at least %d (one batch)", self.spool, len(names), need)
                said = len(names)
            if self.timeout is not None and time.monotonic() - started > self.timeout:
                raise TimeoutError(
                    f"spool {self.spool}: {len(names)} samples after {self.timeout:.0f} s, need at least one batch ({need})"
                )
            if self.interrupted is not None and self.interrupted():
                raise WaitInterrupted(f"stopped while waiting for samples in {self.spool}")
            time.sleep(self.wait)


def spool_names(spool: Path) -> list[str]:
    """The spool's samples; none while the folder is gone (moved, unmounted): the sampler waits."""
    try:
        return enumerate_spool(spool)
    except (FileNotFoundError, NotADirectoryError):
        log.warning("spool %s: no such folder now; waiting for it to come back", spool)
        return []


def rank_batches(order: list[str], batch_size: int, rank: int, world: int, position: int = 0) -> list[list[str]]:
    """This rank's batches of one epoch, from global batch `position` on.

    Global batch k is order[k*B*W : (k+1)*B*W]; rank r takes every W-th name of it from
    the r-th. The shares are disjoint, equal in size, and together they are exactly the
    single-process batches of size B*W (the same samples, so the same global batch).
    A world of one gives the plain batches order[k*B : (k+1)*B].
    """
    span = batch_size * world
    return [order[start + rank : start + span : world]
            for start in range(position * span, len(order) - span + 1, span)]
