"""Names -> a LoaderBatch: the samples read, skipped and counted, collated with their masks packed.

DataLoader workers turn each batch of names the sampler yields (`cuboidtrain.data.sampler`) into
a `LoaderBatch`. A sample's bytes are decoded and checked once, by `shared.sample.decode_packed`.
A name may vanish (the generator evicted it) or hold bad bytes between listing and reading; such
samples are skipped and counted, never a crash. Samples of another shape class or size are
skipped and counted too: a `mix` spool feeds a `box` and a `twobox` trainer at once.

A batch leaves the loader with its masks still bit-packed (8x less to copy) and
`cuboidtrain.data.prepare.prepare_batch` unpacks them on the training device, beside the heat
maps it renders there. Reframing splits the same way (issue 29): a worker finds each sample's
building and its framing (`cuboidtrain.data.reframing.framed`: a few numbers), and
`prepare_batch` carries the batch's masks at the spool's size onto the model's input with them.
"""
from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from cuboidtrain.data.reframing import CutOff, Framed, framed, identity_framing
from cuboidtrain.data.sampler import EpochSampler
from cuboidtrain.fit.masks import Framing
from cuboidtrain.fit.options import DEFAULT_MARGIN
from shared.sample import DamagedSample, PackedSample, Sample, collate, decode_packed, packed_rows
from shared.spool import enumerate_spool, read_sample_bytes

# damaged: a sample whose payload lost the checksum it was written with (bit rot); corrupt: any other fault
SKIP_REASONS = ("vanished", "damaged", "corrupt", "other_shape", "other_size", "cut_off")
REFRAME_MODES = ("never", "always", "other-sizes")


@dataclass(frozen=True)
class Source:
    """A sample as the spool holds it, and the map from the px a batch frames it in to its own
    (the identity for a sample the batch keeps at its own size): what eval fits a cuboid to."""

    sample: Sample
    framing: Framing


@dataclass(frozen=True)
class LoaderBatch:
    """One batch as the loader hands it on, the tensors on the CPU (pinned where asked). The
    tensors are None for a batch that kept no sample.

    `noisy`, `clean`: (B, ceil(source^2 / 8)) uint8, each mask packed at `source` px (`pack_mask`'s
    order; a smaller sample padded with background). `keypoints`: (B, N, 2) float32 in the model's
    px; `ratios`: (B, R) float32. `framing`: (B, 3) float64, each sample's scale and x, y offset
    from its px to the model's, or None for a batch whose samples are all at the model's size."""

    names: list[str]  # the samples kept, in the batch's order
    skipped: dict[str, int]  # samples skipped by reason (SKIP_REASONS)
    vanished: list[str]  # evicted before they were read: the trainer's census counts them
    checksums: list[int]  # each kept sample's payload checksum, as read and checked (the trainer's --ledger)
    noisy: torch.Tensor | None = None
    clean: torch.Tensor | None = None
    keypoints: torch.Tensor | None = None
    ratios: torch.Tensor | None = None
    framing: torch.Tensor | None = None
    source: int = 0  # the packed masks' px
    sources: list[Source] | None = None  # the samples as read (`keep_sources`)

    def pin_memory(self) -> LoaderBatch:
        """The batch with its tensors in pinned memory (DataLoader's `pin_memory` calls this)."""
        pinned = {f: getattr(self, f).pin_memory() for f in ("noisy", "clean", "keypoints", "ratios", "framing")
                  if getattr(self, f) is not None}
        return dataclasses.replace(self, **pinned)


def collate_batch(items: list[tuple[PackedSample, Framing | None]], size: int) -> dict[str, torch.Tensor | int]:
    """Samples of one shape, each framed (a Framing) or at `size` already (None) -> LoaderBatch's
    tensor fields: the plain batch where none is framed (`shared.sample.collate`, packed), else
    both masks at the largest source size with each sample's framing (the identity for one at
    `size`)."""
    samples = [sample for sample, _ in items]
    if all(framing is None for _, framing in items):
        arrays, source = collate(samples, unpack=False), size
    else:
        source = max(s.size for s in samples)
        arrays = {key: packed_rows(samples, key, source) for key in ("noisy", "clean")}
        arrays["keypoints"] = np.stack([s.keypoints for s in samples]).astype(np.float32)
        arrays["ratios"] = np.stack([s.ratios for s in samples]).astype(np.float32)
        framings = [framing or identity_framing(size) for _, framing in items]
        arrays["framing"] = np.array([(f.scale, *f.offset) for f in framings], np.float64)
    return {key: torch.from_numpy(value) for key, value in arrays.items()} | {"source": source}


class SpoolBatches(Dataset):
    """Index: a list of sample names. Item: one LoaderBatch, masks still bit-packed.

    `reframe` (REFRAME_MODES): `always` frames every sample as `infer` frames a mask, at
    `size` (training: train as you infer); `other-sizes` only those of another size (eval:
    the generator's framing where it fits, so the paper's metric stays the paper's); `never`
    skips samples of another size. `margin`: the framing's, as FitOptions' (eval passes its own).
    A batch holding a framed sample keeps its masks at the spool's size, with each sample's
    framing (`collate_batch`): `prepare_batch` frames them on the training device.
    `keep_sources`: each batch also holds its samples as read, with their framings (`Source`).
    `verify=False` skips the samples' checksums: only benchmarks/speed/bench_checksum.py, to
    measure what they cost."""

    def __init__(self, spool: str | Path, shape: str, size: int, reframe: str = "never",
                 margin: float = DEFAULT_MARGIN, keep_sources: bool = False, verify: bool = True):
        if reframe not in REFRAME_MODES:
            raise ValueError(f"reframe {reframe!r}: expected one of {', '.join(REFRAME_MODES)}")
        self.spool, self.shape, self.size, self.reframe, self.margin = Path(spool), shape, size, reframe, margin
        self.keep_sources, self.verify = keep_sources, verify

    def __getitem__(self, names: list[str]) -> LoaderBatch:
        items, kept, vanished, sources, skipped = [], [], [], [], dict.fromkeys(SKIP_REASONS, 0)
        for name in names:
            reason, item = self._read(name)
            if reason:
                skipped[reason] += 1
                if reason == "vanished":
                    vanished.append(name)
                continue
            items.append(item)
            kept.append(name)
            if self.keep_sources:
                sample, framing = item
                sources.append(Source(sample.unpacked(), framing or identity_framing(self.size)))
        tensors = collate_batch(items, self.size) if items else {}
        checksums = [sample.checksum for sample, _ in items]
        return LoaderBatch(kept, skipped, vanished, checksums, **tensors, sources=sources if self.keep_sources else None)

    def _read(self, name: str) -> tuple[str | None, tuple[PackedSample, Framing | None] | None]:
        """(skip reason or None, the sample to batch with its framing: None where it stays at its size)."""
        try:
            data = read_sample_bytes(self.spool, name)
        except OSError:  # a folder or an unreadable file under a sample's name: not a sample
            return "corrupt", None
        if data is None:
            return "vanished", None
        try:
            sample = decode_packed(data, self.verify)  # the checksum and every field checked, once
        except DamagedSample:
            return "damaged", None
        except ValueError:
            return "corrupt", None
        if sample.shape != self.shape:
            return "other_shape", None
        if self.reframe == "always" or (self.reframe == "other-sizes" and sample.size != self.size):
            try:
                found: Framed = framed(sample, self.size, self.margin)
            except CutOff:
                return "cut_off", None
            return None, (found.sample, found.framing)
        if sample.size != self.size:
            return "other_size", None
        return None, (sample, None)

    def __len__(self) -> int:  # DataLoader asks; the sampler decides what an epoch is
        return len(enumerate_spool(self.spool))


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


def _as_is(batch: LoaderBatch) -> LoaderBatch:
    return batch  # SpoolBatches already returns tensors
