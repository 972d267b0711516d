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
there (`cuboidtrain.models.codec`): the paper's x1, x2, x3, x4. Reframing splits the same
way (issue 29): a worker finds each sample's building and its framing (`framed_record`: a
few numbers), and `prepare_batch` carries the batch's masks at the spool's size onto the
model's input with them (`frame_masks`: batched matrix products on the device).

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

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from cuboidtrain.models.codec import render_heatmaps
from cuboidtrain.train.losses import ChainBatch
from cuboidtrain.fit.masks import PIECE_SHARE, SHRINK_BLUR, Framing, framing_of
from cuboidtrain.fit.options import DEFAULT_MARGIN
from shared.sample import BIT_ORDER, BIT_SHIFTS, KEYPOINT_DTYPE, Sample, collate, decode_record, from_record
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


def building(mask: np.ndarray, min_share: float = PIECE_SHARE, min_pixels: int = 16):
    """`cuboidtrain.fit.masks.silhouette` of a uint8 0/1 mask, the same pixels, and their bounding
    box (x, y, w, h); None when no piece is kept. The mask itself (no copy) when every piece is.

    From the pieces' borders (`cv2.findContours`) rather than a labelling: 6x faster at 256 px.
    A piece's pixels are those its outer border walk encloses (Pick: area + steps / 2 + 1) less
    the pixels inside each of its holes' walks (area - steps / 2 + 1)."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    parent, pixels = hierarchy[0][:, 3].tolist(), [0.0] * len(contours)
    for i, contour in enumerate(contours):
        area, steps = abs(cv2.contourArea(contour)), (len(contour) if len(contour) > 1 else 0)
        if parent[i] < 0:
            pixels[i] += area + steps / 2 + 1
        else:
            pixels[parent[i]] -= area - steps / 2 + 1
    outer = [i for i in range(len(contours)) if parent[i] < 0]
    largest = max(pixels[i] for i in outer)
    if largest < min_pixels:
        return None
    least = max(min_pixels, min_share * largest)
    kept = [i for i in outer if pixels[i] >= least]
    boxes = [cv2.boundingRect(contours[i]) for i in kept]
    x, y = min(b[0] for b in boxes), min(b[1] for b in boxes)
    box = (x, y, max(b[0] + b[2] for b in boxes) - x, max(b[1] + b[3] for b in boxes) - y)
    if len(kept) == len(outer):
        return mask, box
    return _without(mask, contours, hierarchy[0], [i for i in outer if pixels[i] < least], pixels), box


def _without(mask: np.ndarray, contours, links: np.ndarray, dropped: list[int], pixels: list[float]) -> np.ndarray:
    """`mask` less its `dropped` pieces (outer borders of `contours`, `links` their hierarchy)."""
    if all(links[i][2] < 0 for i in dropped):  # no dropped piece has a hole another piece could lie in
        kept = mask.copy()
        cv2.drawContours(kept, [contours[i] for i in dropped], -1, 0, thickness=cv2.FILLED)
        return kept
    # Each outer border filled with 1 (kept) or 0, larger fills first: a piece inside another's hole wins.
    canvas, outer = np.zeros_like(mask), [i for i in range(len(contours)) if links[i][3] < 0]
    for i in sorted(outer, key=lambda i: -pixels[i]):
        cv2.drawContours(canvas, contours, i, 0 if i in dropped else 1, thickness=cv2.FILLED)
    return canvas & mask


def framed_record(record: dict, size: int, margin: float = DEFAULT_MARGIN) -> dict:
    """A decoded record as `infer` would see it (train as you infer), all but its pixels: its noisy
    mask's building (`building`: its pieces, together) framed at `size` as
    `cuboidtrain.fit.masks.frame` frames it. `noisy` becomes the building's packed bits, `keypoints`
    the (N, 2) float64 keypoints in the model's px, and `framing` the Framing (the map from the
    sample's px) by which `prepare_batch` carries both masks onto the model's input. A generated
    sample is framed by its noisy silhouette; a real mask can only be framed by what is visible of
    it. Raises CutOff for a sample no framing of its visible part can hold."""
    source = record["size"]
    noisy = np.unpackbits(np.frombuffer(record["noisy"], np.uint8), count=source * source,
                          bitorder=BIT_ORDER).reshape(source, source)
    found = building(noisy)
    if found is None:
        raise CutOff("no visible piece to frame")
    kept, box = found
    framing = framing_of(box, size, margin, (source, source))
    keypoints = framing.to_model(np.frombuffer(record["keypoints"], KEYPOINT_DTYPE).reshape(-1, 2))
    reach = MAX_OUTSIDE * size
    if keypoints.min() < -0.5 - reach or keypoints.max() > size - 0.5 + reach:
        raise CutOff(f"a corner lies more than {reach:g} px outside the frame")
    bits = record["noisy"] if kept is noisy else np.packbits(kept, bitorder=BIT_ORDER).tobytes()
    return {**record, "noisy": bits, "keypoints": keypoints, "framing": framing}


def collate_framed(records: list[dict], size: int) -> dict[str, np.ndarray | int]:
    """Records of one shape, each framed (`framed_record`) or at `size` already (framed by the
    identity) -> the batch `prepare_batch` frames on the device: both masks still packed, at the
    largest source size `source` (smaller ones padded with background), `keypoints` (B, N, 2) and
    `ratios` (B, R) float32 as `collate` gives them, and `framing` (B, 3) float64: each sample's
    scale, x offset and y offset (`Framing`)."""
    identity = Framing(1.0, (0.0, 0.0), size, (size, size))
    framings = [r.get("framing", identity) for r in records]
    source = max(r["size"] for r in records)
    batch = {key: _packed_at(records, key, source) for key in ("noisy", "clean")}
    batch["keypoints"] = np.stack([np.frombuffer(r["keypoints"], KEYPOINT_DTYPE).reshape(-1, 2)
                                   if isinstance(r["keypoints"], bytes) else r["keypoints"] for r in records])
    batch["keypoints"] = batch["keypoints"].astype(np.float32)
    geometry = get_shape(records[0]["shape"])
    batch["ratios"] = np.stack([geometry.ratio_vector(r["ratios"]) for r in records]).astype(np.float32)
    batch["framing"] = np.array([(f.scale, *f.offset) for f in framings], np.float64)
    return batch | {"source": source}


def _packed_at(records: list[dict], key: str, source: int) -> np.ndarray:
    """(B, ceil(source^2 / 8)) uint8: each record's `key` mask packed at `source` px, padded below and right."""
    if all(r["size"] == source for r in records):  # the usual batch: the bytes as read, joined
        return np.frombuffer(bytearray().join(r[key] for r in records), np.uint8).reshape(len(records), -1)
    canvas = np.zeros((len(records), source, source), np.uint8)
    for canvas_row, r in zip(canvas, records):
        own = np.unpackbits(np.frombuffer(r[key], np.uint8), count=r["size"] ** 2, bitorder=BIT_ORDER)
        canvas_row[: r["size"], : r["size"]] = own.reshape(r["size"], r["size"])
    return np.packbits(canvas.reshape(len(records), -1), axis=1, bitorder=BIT_ORDER)


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
    A batch holding a framed sample keeps its masks at the spool's size, with each sample's
    framing (`collate_framed`): `prepare_batch` frames them on the training device.
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
        if any("framing" in r for r in records):
            batch = collate_framed(records, self.size)
        else:
            batch = collate(records, unpack=False) if records else {}
        batch = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in batch.items()}
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
            try:
                framed = framed_record(record, self.size, self.margin)
            except CutOff:
                return "cut_off", None, None
            return None, framed, Source(from_record(record), framed["framing"]) if self.keep_sources else None
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


def unpack_bits(packed: torch.Tensor, count: int) -> torch.Tensor:
    """(..., n) uint8 packed bits (`shared.sample.pack_mask`'s order) -> (..., count) uint8 0/1 along
    the last axis, on the tensor's device (numpy's unpacking on the CPU: 8x faster than torch's shifts)."""
    if packed.device.type == "cpu":
        return torch.from_numpy(np.unpackbits(packed.numpy(), axis=-1, count=count, bitorder=BIT_ORDER))
    bits = (packed.unsqueeze(-1) >> _BIT_SHIFTS.to(packed.device)) & 1  # (..., n, 8)
    return bits.flatten(-2)[..., :count]


def unpack_masks(packed: torch.Tensor, size: int) -> torch.Tensor:
    """(B, ceil(size*size/8)) uint8 packed bits -> (B, 1, size, size) float32, +1 object / -1
    background. In torch, so that it runs on the training device."""
    return unpack_bits(packed, size * size).view(-1, 1, size, size).float() * 2 - 1


# ---- framing on the device ----------------------------------------------------------------
# `cuboidtrain.fit.masks.warp` carries a mask onto the model's input by a Framing: a Gaussian of std
# 0.29 / scale px when shrinking (cv2's, of radius round(8 std + 1) // 2 px), then bilinear sampling
# at the model's pixel centres, >= 0.5. Both are separable: model row v of a mask is a weighted sum
# of the source rows near its centre, whose weights are the tent's lerp of the discrete Gaussian
# (`_axis_weights`), and so are its columns. So a batch takes two batched matrix products: over the
# rows, chunk by chunk of CHUNK model rows and the source rows they reach (`_pass`; a blur of every
# source pixel would cost 6x more), then over the columns, alike on the transposed result or at once
# (`DENSE_MOST`).
CHUNK = 8  # model rows per product: fewer waste less of the source rows read, more run faster
GROUP = {"cpu": 8}  # samples framed together by device type: on a CPU what a group reads stays in its cache
DEVICE_GROUP = 64  # elsewhere (a GPU): few launches, bounded memory
# Model px up to which the columns' pass is one product over every source column, by device type;
# above it the columns go chunk by chunk like the rows. On a CPU (with one torch thread or two)
# the chunks win at every size, as OpenCV transposes the rows' result 14x faster than torch
# copies it (`_by_columns`; frame_masks 1-9% faster at 64 px, 22% at 128, BENCHMARKS.md).
# Elsewhere the single product up to 64 px stays, as it was chosen for a CPU (not measured on a GPU).
DENSE_MOST = {"cpu": 0}
DEVICE_DENSE_MOST = 64


def frame_masks(noisy: torch.Tensor, clean: torch.Tensor, framing: torch.Tensor, source: int,
                size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch's packed (B, ceil(source^2 / 8)) masks carried onto the model's `size` px input by
    their framings (B, 3: scale, x offset, y offset; `collate_framed`), both as `warp` carries a
    mask: (B, 1, size, size) float32 +1 / -1 each. On the masks' device, in float32 whatever the autocast."""
    framing, batch = framing.to(noisy.device, torch.float64), noisy.shape[0]
    group = GROUP.get(noisy.device.type, DEVICE_GROUP)
    with torch.autocast(noisy.device.type, enabled=False):
        scale = framing[:, 0].repeat(2)  # both axes at once: y (rows), then x (columns)
        pixels, weights, reach = _axis_weights(torch.cat([framing[:, 2], framing[:, 1]]), scale, source, size)
        framed = torch.cat([_frame_group(noisy[at : at + group], clean[at : at + group], source,
                                         *_windows(pixels, weights, reach, at, min(group, batch - at), batch))
                            for at in range(0, batch, group)])
    signed = torch.empty(2, batch, 1, size, size, device=noisy.device)  # x1 and x2, each contiguous
    signed.copy_(framed[:, :, None, :size, :size].transpose(0, 1)).mul_(2).sub_(1)
    return signed[0], signed[1]


def _windows(pixels: torch.Tensor, weights: torch.Tensor, reach: torch.Tensor, at: int, count: int,
             batch: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """`_axis_weights`' windows of `count` samples from `at`, along y and then along x (its second
    half), only as long as these samples reach."""
    length = int(reach[at : at + count].max())
    return tuple([part[first : first + count, ..., :length] for part in (pixels, weights)] for first in (at, batch + at))


def _frame_group(noisy: torch.Tensor, clean: torch.Tensor, source: int, rows: list[torch.Tensor],
                 cols: list[torch.Tensor]) -> torch.Tensor:
    """`frame_masks` of a few samples, given `_axis_weights` along y (`rows`) and x (`cols`):
    (B, 2, C * CHUNK, C * CHUNK) bool, noisy then clean."""
    if source % 8 == 0:  # both masks' bytes row by row, unpacked at once: (B, source, 2 source)
        pair = unpack_bits(torch.cat([noisy.view(-1, source, source // 8), clean.view(-1, source, source // 8)], 2),
                           2 * source)
    else:
        pair = torch.cat([unpack_bits(m, source * source).view(-1, source, source) for m in (noisy, clean)], 2)
    batch, spread = pair.shape[0], rows[0].shape[1] * CHUNK  # model px in whole chunks, >= size
    across = _pass(pair, *rows)  # model y by (mask, source x)
    if spread <= DENSE_MOST.get(pair.device.type, DEVICE_DENSE_MOST):  # every source column the group reaches, at once
        low, high = (int(bound) for bound in torch.aminmax(cols[0]))
        framed = torch.bmm(across.view(batch, 2 * spread, source)[:, :, low : high + 1],
                           _dense(cols[0] - low, cols[1], high + 1 - low))
        return framed.view(batch, spread, 2, spread).transpose(1, 2) >= 0.5
    # source x by (mask, model y): the image the columns' pass reads, both masks' chunks in one product
    framed = _pass(_by_columns(across, source), *cols).view(batch, spread, 2, spread)  # model x by (mask, model y)
    return framed.permute(0, 2, 3, 1) >= 0.5


def _by_columns(across: torch.Tensor, source: int) -> torch.Tensor:
    """The rows' pass (B, model y, (mask, source x)) -> (B, source x, (mask, model y)), contiguous.
    On a CPU by OpenCV's blocked transposes (each mask's into its columns), 14x faster than torch's
    copy of the permuted view, which any other device does."""
    batch, spread = across.shape[:2]
    if across.device.type != "cpu":
        return across.view(batch, spread, 2, source).permute(0, 3, 2, 1).reshape(batch, source, 2 * spread)
    image = across.new_empty(batch, source, 2 * spread)
    for rows, columns in zip(across.numpy(), image.numpy()):
        for mask in range(2):
            cv2.transpose(rows[:, mask * source : (mask + 1) * source], columns[:, mask * spread : (mask + 1) * spread])
    return image


def _dense(pixels: torch.Tensor, weights: torch.Tensor, source: int) -> torch.Tensor:
    """`_axis_weights`' chunks (B, C, L), (B, C, CHUNK, L) -> (B, source, C * CHUNK): each model
    px's weights over every source px, the right factor of one product."""
    batch, chunks = pixels.shape[:2]
    dense = torch.zeros(batch, chunks, CHUNK, source, device=weights.device)
    dense.scatter_add_(3, pixels[:, :, None, :].expand(-1, -1, CHUNK, -1), weights)
    return dense.view(batch, chunks * CHUNK, source).transpose(1, 2)


def _pass(image: torch.Tensor, pixels: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """One separable pass over (B, H, W) `image`: for each chunk of CHUNK model px, the weighted
    sums of the image rows `pixels` (B, C, L) by `weights` (B, C, CHUNK, L) -> (B, C * CHUNK, W)."""
    batch, height, width = image.shape
    chunks, reach = pixels.shape[1:]
    base = torch.arange(batch, device=image.device)[:, None, None] * height
    windows = image.reshape(batch * height, width).index_select(0, (pixels + base).view(-1))
    windows = windows.view(batch * chunks, reach, width).float()
    return torch.bmm(weights.reshape(batch * chunks, CHUNK, reach), windows).view(batch, chunks * CHUNK, width)


def _axis_weights(offset: torch.Tensor, scale: torch.Tensor, source: int,
                  size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Along one axis, per sample: for each chunk of CHUNK model px, the L source px it reaches
    (B, C, L) and their weights (B, C, CHUNK, L), the tent's lerp of the discrete Gaussian at
    each model px's centre in the source (`model = scale * source + offset`); and (B,) how many
    of the L each sample's chunks reach (the rest weigh 0)."""
    batch, chunks = offset.shape[0], -(-size // CHUNK)
    blur = torch.where(scale < 1, SHRINK_BLUR / scale, torch.zeros_like(scale))
    radius = torch.where(blur > 0, torch.round(blur * 8 + 1).long() | 1, torch.ones_like(blur, dtype=torch.long)) // 2
    needed = torch.ceil((CHUNK - 1) / scale).long() + 2 * radius + 2  # what the lerp of the taps reaches
    reach = int(needed.max())
    centre = (torch.arange(chunks * CHUNK, device=offset.device, dtype=torch.float64) - offset[:, None]) / scale[:, None]
    centre = centre.view(batch, chunks, CHUNK)  # source px
    first = centre[:, :, :1].floor() - radius[:, None, None]  # (B, C, 1): each chunk's first source px
    whole = (centre - first).floor()  # in [0, reach): the source px just below each centre, from `first`
    taps = _gaussian(blur, radius, reach)  # (B, 2 reach + 1): the Gaussian at -reach .. reach px
    # Source px first + l weighs taps(whole - l) (1 - frac) + taps(whole - l + 1) frac: a slice of
    # the (symmetric) taps, reversed, from reach - whole - 1.
    start = (reach - 1 - whole.long()).view(batch, -1)
    window = taps.unfold(1, reach + 1, 1)[torch.arange(batch, device=offset.device)[:, None], start]
    window = window.view(batch, chunks, CHUNK, reach + 1)
    weights = torch.lerp(window[..., 1:], window[..., :-1], (centre - first - whole).float()[..., None])
    pixels = first.long() + torch.arange(reach, device=offset.device)  # (B, C, L)
    inside = ((pixels >= 0) & (pixels < source)).to(weights.dtype)  # a source px off the image weighs 0
    return pixels.clamp(0, source - 1), weights.mul_(inside[:, :, None, :]), needed


def _gaussian(blur: torch.Tensor, radius: torch.Tensor, reach: int) -> torch.Tensor:
    """(B,) std in source px (0: none) and radius (cv2's for float images) -> (B, 2 reach + 1)
    float32: each sample's normalised discrete Gaussian at -reach .. reach px."""
    offsets, blur = torch.arange(-reach, reach + 1, device=blur.device, dtype=torch.float32), blur.float()[:, None]
    # the exponent clamped at -40 (exp(-8) at the radius): no exp underflows, 13x slower on a CPU;
    # beyond the radius the taps are 0 anyway
    taps = torch.where(blur > 0, torch.exp((-offsets**2 / (2 * blur.clamp(min=1e-6) ** 2)).clamp(min=-40.0)),
                       (offsets == 0).float())
    taps = taps * (offsets.abs() <= radius[:, None])
    return taps / taps.sum(1, keepdim=True)


def prepare_batch(batch: dict, device: torch.device, sigma: float, size: int) -> ChainBatch:
    """A loader batch -> the paper's x1 (noisy), x2 (clean), x3 (heat maps), x4 (keypoints), ratios;
    a batch with framings (`collate_framed`) framed at `size` on the device (`frame_masks`)."""
    non_blocking = device.type == "cuda"
    keypoints = batch["keypoints"].to(device, non_blocking=non_blocking)
    noisy = batch["noisy"].to(device, non_blocking=non_blocking)
    clean = batch["clean"].to(device, non_blocking=non_blocking)
    if "framing" in batch:
        x1, x2 = frame_masks(noisy, clean, batch["framing"], batch["source"], size)
    else:
        x1, x2 = unpack_masks(noisy, size), unpack_masks(clean, size)
    return ChainBatch(
        x1=x1,
        x2=x2,
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
