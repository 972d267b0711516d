"""Spool-backed data loading: the spool is enumerated afresh at every epoch (paper 3.3.2).

The sampler runs in the main process. At each epoch's start it lists the spool,
shuffles the names with a seed derived from (run seed, epoch) and yields
batches of names; DataLoader workers turn a batch of names into packed arrays.
So the loader's state is just (epoch, order, position): a checkpoint stores it
and `--resume` continues with the very next batch. Only the sampler moves that
state; the trainer tells it what it did (`advance`, `end_epoch`) and asks where it
stands (`where`, `snapshot`).

A name may vanish (the generator evicted it) or hold bad bytes between listing
and reading; such samples are skipped and counted, never a crash. Samples of
another shape class or size are skipped and counted too: a `mix` spool feeds a
`box` and a `twobox` trainer at once.

A batch leaves the loader with its masks still bit-packed (8x less to copy) and
`prepare_batch` unpacks them on the training device, beside the heat maps it renders
there (`cuboidtrain.models.codec`): the paper's x1, x2, x3, x4.

Under torchrun each rank takes its strided share of every global batch (see
`cuboidtrain.train.distributed`); the state (epoch, order, position) is the same on
every rank, so one checkpoint resumes them all.
"""
from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from cuboidtrain.models.codec import render_heatmaps
from cuboidtrain.train.losses import ChainBatch
from cuboidtrain.fit.masks import Framing, frame, silhouette, warp
from cuboidtrain.fit.options import DEFAULT_MARGIN
from shared.sample import BIT_SHIFTS, Sample, collate, decode_record, from_record, to_record
from shared.shapes import get_shape
from shared.spool import enumerate_spool, name_time, read_sample_bytes

log = logging.getLogger(__name__)

SKIP_REASONS = ("vanished", "corrupt", "other_shape", "other_size", "cut_off")
# A reframed sample whose corner lies further than this fraction of the size outside the frame is
# skipped: what is visible of it is a fragment, and no Tabulator could reach the corner.
MAX_OUTSIDE = 0.125


REFRAME_MODES = ("never", "always", "other-sizes")


class CutOff(Exception):
    """A sample whose visible part cannot frame the whole shape (see MAX_OUTSIDE)."""


def frame_as_infer(sample: Sample, size: int, margin: float = DEFAULT_MARGIN) -> tuple[Sample, Framing]:
    """The sample as `infer` would see it (train as you infer): the noisy mask's building
    (`cuboidtrain.fit.masks.silhouette`: its pieces, together) framed at `size` by
    `cuboidtrain.fit.masks.frame`, the clean mask and the keypoints carried by the same map. A
    generated sample is framed by its clean silhouette; a real mask can only be framed by what
    is visible of it. Returns the framed sample and its Framing (the map back to the sample's px)."""
    building = silhouette(sample.noisy)
    if building is None:
        raise CutOff("no visible piece to frame")
    framed, framing = frame(building, size, margin)
    keypoints = framing.to_model(sample.keypoints)
    reach = MAX_OUTSIDE * size
    if keypoints.min() < -0.5 - reach or keypoints.max() > size - 0.5 + reach:
        raise CutOff(f"a corner lies more than {reach:g} px outside the frame")
    return replace(sample, size=size, noisy=framed, clean=warp(sample.clean, framing), keypoints=keypoints), framing


@dataclass(frozen=True)
class Source:
    """A sample as the spool holds it, and the map from the px a batch frames it in to its own
    (the identity for a sample the batch keeps at its own size): what eval fits a cuboid to."""

    sample: Sample
    framing: Framing


class SpoolBatches(Dataset):
    """Index: a list of sample names. Item: one collated batch, masks still bit-packed.

    `reframe` (REFRAME_MODES): `always` frames every sample as `infer` frames a mask, at
    `size` (training: train as you infer); `other-sizes` only those of another size (eval:
    the generator's framing where it fits, so the paper's metric stays the paper's); `never`
    skips samples of another size. `margin`: the framing's, as FitOptions' (eval passes its own).
    `keep_sources`: each batch also holds its samples as read, with their framings (`Source`)."""

    def __init__(self, spool: str | Path, shape: str, size: int, reframe: str = "never",
                 margin: float = DEFAULT_MARGIN, keep_sources: bool = False):
        if reframe not in REFRAME_MODES:
            raise ValueError(f"reframe {reframe!r}: expected one of {', '.join(REFRAME_MODES)}")
        self.spool, self.shape, self.size, self.reframe, self.margin = Path(spool), shape, size, reframe, margin
        self.keep_sources = keep_sources

    def __getitem__(self, names: list[str]) -> dict:
        records, kept, vanished, sources, skipped = [], [], [], [], dict.fromkeys(SKIP_REASONS, 0)
        for name in names:
            reason, record, source = self._read(name)
            if reason:
                skipped[reason] += 1
                if reason == "vanished":
                    vanished.append(name)
                continue
            records.append(record)
            kept.append(name)
            sources.append(source)
        batch = collate(records, unpack=False) if records else {}
        batch = {k: torch.from_numpy(v) for k, v in batch.items()}
        batch["names"] = kept
        batch["vanished"] = vanished  # evicted before they were read: the trainer's census counts them
        batch["skipped"] = skipped
        if self.keep_sources:
            batch["sources"] = sources
        return batch

    def _read(self, name: str) -> tuple[str | None, dict | None, Source | None]:
        """(skip reason or None, the record to batch, its Source where `keep_sources`)."""
        try:
            data = read_sample_bytes(self.spool, name)
        except OSError:  # a folder or an unreadable file under a sample's name: not a sample
            return "corrupt", None, None
        if data is None:
            return "vanished", None, None
        try:
            record = decode_record(data)
            # decode_record checks the byte fields, not the ratio record; collate needs it whole
            get_shape(record["shape"]).ratio_vector(record["ratios"])
        except (ValueError, KeyError, TypeError):
            return "corrupt", None, None
        if record["shape"] != self.shape:
            return "other_shape", None, None
        if self.reframe == "always" or (self.reframe == "other-sizes" and record["size"] != self.size):
            sample = from_record(record)
            try:
                framed, framing = frame_as_infer(sample, self.size, self.margin)
            except CutOff:
                return "cut_off", None, None
            return None, to_record(framed), Source(sample, framing) if self.keep_sources else None
        if record["size"] != self.size:
            return "other_size", None, None
        if not self.keep_sources:
            return None, record, None
        return None, record, Source(from_record(record), Framing(1.0, (0.0, 0.0), self.size, (self.size, self.size)))

    def __len__(self) -> int:  # DataLoader asks; the sampler decides what an epoch is
        return len(enumerate_spool(self.spool))


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
            from cuboidtrain.train.distributed import rank_batches

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


def make_loader(spool: str | Path, shape: str, size: int, batch_size: int, seed: int, workers: int,
                pin_memory: bool = False, timeout: float | None = None,
                worker_init_fn=None, reframe: str = "never", **sampler_options) -> tuple[DataLoader, EpochSampler]:
    """`sampler_options`: EpochSampler's rank, world, list_spool and interrupted (torchrun)."""
    sampler = EpochSampler(spool, batch_size, seed, timeout=timeout, **sampler_options)
    loader = DataLoader(
        SpoolBatches(spool, shape, size, reframe),
        sampler=sampler,
        batch_size=None,  # the sampler yields whole batches of names
        num_workers=workers,
        pin_memory=pin_memory,
        persistent_workers=workers > 0,
        prefetch_factor=4 if workers > 0 else None,
        collate_fn=_as_is,
        worker_init_fn=worker_init_fn,
    )
    return loader, sampler


@contextlib.contextmanager
def workers_stopped(loader: DataLoader):
    """The loader's worker processes stopped on the way out, however the block ends. Persistent
    workers otherwise live as long as their iterator, and an exception's traceback keeps that
    alive: until interpreter exit, where joining them can hang for good (issue 22)."""
    try:
        yield loader
    finally:
        iterator = getattr(loader, "_iterator", None)
        if iterator is not None and hasattr(iterator, "_shutdown_workers"):
            iterator._shutdown_workers()
        loader._iterator = None


def _as_is(batch: dict) -> dict:
    return batch  # SpoolBatches already returns tensors


_BIT_SHIFTS = torch.tensor(BIT_SHIFTS, dtype=torch.uint8)  # shared.sample's bit order, one shift per pixel of a byte


def unpack_masks(packed: torch.Tensor, size: int) -> torch.Tensor:
    """(B, ceil(size*size/8)) uint8 packed bits (`shared.sample.pack_mask`) -> (B, 1, size, size)
    float32, +1 object / -1 background. In torch, so that it runs on the training device."""
    bits = (packed.unsqueeze(-1) >> _BIT_SHIFTS.to(packed.device)) & 1  # (B, bytes, 8)
    bits = bits.reshape(packed.shape[0], -1)[:, : size * size]
    return bits.view(-1, 1, size, size).float() * 2 - 1


def prepare_batch(batch: dict, device: torch.device, sigma: float, size: int) -> ChainBatch:
    """A loader batch -> the paper's x1 (noisy), x2 (clean), x3 (heat maps), x4 (keypoints), ratios."""
    non_blocking = device.type == "cuda"
    keypoints = batch["keypoints"].to(device, non_blocking=non_blocking)
    return ChainBatch(
        x1=unpack_masks(batch["noisy"].to(device, non_blocking=non_blocking), size),
        x2=unpack_masks(batch["clean"].to(device, non_blocking=non_blocking), size),
        x3=render_heatmaps(keypoints, size, sigma),
        x4=keypoints,
        ratios=batch["ratios"].to(device, non_blocking=non_blocking),
    )


class FreshnessMeter:
    """Measures how fresh each batch trained on is (its samples' age, how often each was used
    before) from a use count per sample name (the status shows the reading: status.BatchFreshness)."""

    def __init__(self):
        self.uses: dict[str, int] = {}

    def observe(self, names: list[str], now: float | None = None) -> tuple[float, float]:
        """Counts one more use of each name; returns (mean age s, mean earlier uses) of the batch."""
        now = time.time() if now is None else now
        if not names:
            return 0.0, 0.0
        ages = [now - name_time(n) for n in names]
        earlier = [self.uses.get(n, 0) for n in names]
        for n in names:
            self.uses[n] = self.uses.get(n, 0) + 1
        return float(np.mean(ages)), float(np.mean(earlier))

    def forget_except(self, names: list[str]) -> None:
        """Drop counts of evicted samples so memory stays bounded by the spool."""
        live = set(names)
        self.uses = {n: c for n, c in self.uses.items() if n in live}
