"""The training sample and its versioned byte format.

This module is the only code that turns samples into bytes and back (STYLE.md).
A sample is one msgpack map: its format, its version, and its payload (the sample's fields,
itself a msgpack map) with the payload's checksum (XXH3-64), so that a bit flipped after writing (a
disk, a network file system, a copy) is found on read rather than trained on. Masks are bit-packed (`np.packbits`, row-major,
BIT_ORDER within a byte), keypoints are little-endian float64, so a 256x256
sample is about 17 KB. Heat maps are not stored: they are a function of the
keypoints and the trainer renders them on its device, where it also unpacks the
masks (in torch, by BIT_SHIFTS: the bit order is stated here and nowhere else).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgpack
import numpy as np
import xxhash

from shared.shapes import RATIO_KEYS, SHAPES, get_shape

FORMAT = "cuboid-fit/sample"
# 3: the payload carries its XXH3-64 (xxhash's xxh3_64, seed 0): 0.4 us for a 256 px sample's 17 KB
# here; the loader keeps 0.96-0.99x of its samples/s without it at 256 px (0.98-0.99x at 64), the
# generator 0.96-0.99x. Version 2 carried zlib's CRC-32, 4.2 us: the loader kept 0.87-0.88x at 256
# px, against the 0.95x asked (issue 39; BENCHMARKS.md, "The samples' checksums"). The CRC found
# every single flipped bit for certain; XXH3-64 misses a change, one bit or many, with odds of 2^-64.
# Older versions are refused, not read unchecked: a spool is drawn afresh in minutes.
VERSION = 3
REFUSED_VERSIONS = {1: "version 1 carried no checksum", 2: "version 2's checksum was a CRC-32"}
KEYPOINT_DTYPE = "<f8"  # little-endian float64, (N, 2) px row-major
BIT_ORDER = "big"  # np.packbits' default: a byte's first pixel is its most significant bit
# The right shift that brings each of a byte's 8 pixels, first pixel first, down to bit 0:
# for unpacking without numpy (the trainer unpacks a batch on its device, in torch).
BIT_SHIFTS = (7, 6, 5, 4, 3, 2, 1, 0) if BIT_ORDER == "big" else (0, 1, 2, 3, 4, 5, 6, 7)
# What a reader accepts beyond the byte lengths (docs/contract.md, "Sample format"): a sample
# outside these bounds is no picture of a building, and one NaN in a batch ruins a training run.
MAX_SIZE = 4096  # px: the generator's largest --size
# How far outside the image a keypoint may lie, as a fraction of the size. The generator frames
# the whole silhouette inside the image, so its keypoints lie within it; a hidden corner of another
# writer's sample may lie beyond an edge, and the trainer cuts off any beyond 1/8 of the size
# (cuboidtrain.data.reframing.MAX_OUTSIDE), so this bound is only for values no framing explains.
KEYPOINT_REACH = 0.5
RATIO_RANGE = (1e-3, 1e3)  # depth/height and width/height: positive, and no part a thousand times flatter


class CorruptSample(ValueError):
    """A sample of this format and version whose fields cannot be right. `reason` names the field
    and the fault without the values (what a census counts by); the message adds the values."""

    def __init__(self, field: str, fault: str, detail: str):
        super().__init__(f"corrupt sample: {field}: {fault} ({detail})")
        self.reason = f"{field}: {fault}"


class DamagedSample(CorruptSample):
    """A sample whose payload no longer has the checksum it was written with: its bytes changed
    after writing (bit rot, a torn copy). Readers skip and count it under its own reason."""

    def __init__(self, found: int, written: int):
        super().__init__("checksum", "mismatch", f"XXH3-64 {found:016x}, written as {written:016x}")


@dataclass(frozen=True, eq=False)
class Sample:
    """One synthetic sample: the paper's (x1, x2, x4) plus how it was drawn.

    Masks are boolean (True = building); `signed` gives the paper's +1/-1 form.
    Keypoints are (N, 2) pixels, x right and y down, integer = pixel centre.
    """

    shape: str
    size: int  # px, masks are size x size
    seed: int
    keypoints: np.ndarray  # (N, 2) float64
    ratios: dict  # the nested ratio record (docs/contract.md, "Ratios")
    noisy: np.ndarray  # (size, size) bool: occluded and contour-noised, the Refiner's input x1
    clean: np.ndarray  # (size, size) bool: the silhouette, the Refiner's target x2
    params: dict = field(default_factory=dict)  # everything drawn: scene, occlusion, noise

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sample):
            return NotImplemented
        return encode(self) == encode(other)


def signed(mask: np.ndarray) -> np.ndarray:
    """A boolean mask as the paper's float32 +1 (object) / -1 (background); a grey one (each
    pixel's covered share, in [0, 1]: `cuboidtrain.fit.masks.levels`) onto [-1, 1] alike."""
    if mask.dtype == bool:
        return np.where(mask, np.float32(1), np.float32(-1))
    return np.asarray(mask, np.float32) * 2 - 1


def pack_mask(mask: np.ndarray) -> bytes:
    """A (size, size) bool mask -> ceil(size^2 / 8) bytes, row-major, BIT_ORDER within a byte."""
    return np.packbits(mask, bitorder=BIT_ORDER).tobytes()


def unpack_mask(packed: bytes, size: int) -> np.ndarray:
    """`pack_mask`'s bytes -> the (size, size) bool mask."""
    bits = np.unpackbits(np.frombuffer(packed, np.uint8), count=size * size, bitorder=BIT_ORDER)
    return bits.reshape(size, size).view(bool)


def encode(sample: Sample) -> bytes:
    """Sample -> bytes: the payload (its fields) and the payload's checksum, in one map."""
    return pack_record(to_record(sample))


def pack_record(record: dict) -> bytes:
    """A record as `decode_record` gives it -> bytes, its payload (every key but the format and
    version) with its checksum. Unchecked: `encode` checks the record first (`to_record`); tests
    write records a reader must refuse through it."""
    outer = {key: record[key] for key in ("format", "version") if key in record}
    payload = msgpack.packb({key: value for key, value in record.items() if key not in outer}, use_bin_type=True)
    return msgpack.packb({**outer, "checksum": checksum(payload), "payload": payload}, use_bin_type=True)


def checksum(payload: bytes) -> int:
    """The payload's checksum as a sample carries it: XXH3-64 (seed 0), an unsigned 64-bit int."""
    return xxhash.xxh3_64_intdigest(payload)


def to_record(sample: Sample) -> dict:
    """Sample -> the record `decode_record` gives for its bytes: masks packed, keypoints as bytes."""
    n = get_shape(sample.shape).num_keypoints
    keypoints = np.ascontiguousarray(sample.keypoints, dtype=KEYPOINT_DTYPE)
    if keypoints.shape != (n, 2):
        raise ValueError(f"keypoints have shape {keypoints.shape}, expected ({n}, 2) for {sample.shape!r}")
    for name in ("noisy", "clean"):
        mask = getattr(sample, name)
        if mask.shape != (sample.size, sample.size):
            raise ValueError(f"{name} mask is {mask.shape}, expected ({sample.size}, {sample.size})")
    record = {
        "format": FORMAT,
        "version": VERSION,
        "shape": sample.shape,
        "size": sample.size,
        "seed": sample.seed,
        "keypoints": keypoints.tobytes(),
        "ratios": sample.ratios,
        "noisy": pack_mask(sample.noisy),
        "clean": pack_mask(sample.clean),
        "params": sample.params,
    }
    check_record(record)  # a writer never makes a sample its readers refuse
    return record


def decode_record(data: bytes, verify: bool = True) -> dict:
    """Bytes -> the raw record; see `decode_checked`, whose record it is."""
    return decode_checked(data, verify)[0]


def decode_checked(data: bytes, verify: bool = True) -> tuple[dict, int]:
    """Bytes -> the raw record (format, version and the payload's fields) and the payload's checksum,
    checked for format, version, checksum and every field, masks still packed. `verify=False` skips the checksum
    alone (benchmarks/speed/bench_checksum.py measures what it costs; nothing else passes it).

    Raises ValueError naming what was found and what was expected; DamagedSample (a
    CorruptSample) when the payload's checksum is not the one written.
    """
    outer = _unpack(data, "sample")
    if not isinstance(outer, dict) or outer.get("format") != FORMAT:
        found = outer.get("format") if isinstance(outer, dict) else type(outer).__name__
        raise ValueError(f"not a cuboid-fit sample: format {found!r}, expected {FORMAT!r}")
    version = outer.get("version")
    if type(version) is not int or version != VERSION:  # True == 1 in Python: the type too
        why = f" ({REFUSED_VERSIONS[version]}: draw the spool afresh)" if version in REFUSED_VERSIONS else ""
        raise ValueError(f"sample format version {version!r} is not supported: expected {VERSION}{why}")
    payload, written = outer.get("payload"), outer.get("checksum")
    if not isinstance(payload, bytes) or not _integer(written):
        raise CorruptSample("checksum", "missing", f"a payload of {type(payload).__name__} and a checksum of {written!r}")
    found = checksum(payload) if verify else written
    if found != written:
        raise DamagedSample(found, written)
    fields = _unpack(payload, "payload")
    if not isinstance(fields, dict):
        raise CorruptSample("payload", "not a map", f"a {type(fields).__name__}")
    record = {"format": FORMAT, "version": VERSION, **fields}
    check_record(record)
    return record, found


def _unpack(data: bytes, what: str):
    try:
        return msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack raises several unrelated types for bad bytes
        raise ValueError(f"corrupt {what}: not a msgpack map ({type(exc).__name__}: {exc})") from None


def check_record(record: dict) -> None:
    """Every field of a sample record of this version: types, byte lengths, and values (finite
    keypoints within KEYPOINT_REACH of the image, ratios in RATIO_RANGE). Raises CorruptSample.

    The generator's hot path and the trainer's reader both run it: a few microseconds a sample
    (a min and a max over the keypoints, which NaN fails too)."""
    for key in ("shape", "size", "seed", "keypoints", "ratios", "noisy", "clean", "params"):
        if key not in record:
            raise CorruptSample(key, "missing", f"a sample has {', '.join(sorted(map(str, record)))}")
    shape, size, seed = record["shape"], record["size"], record["seed"]
    if not isinstance(shape, str) or shape not in SHAPES:
        raise CorruptSample("shape", "unknown", f"{shape!r}, expected one of {sorted(SHAPES)}")
    if not _integer(size) or not 1 <= size <= MAX_SIZE:
        raise CorruptSample("size", "out of range", f"{size!r}, expected an integer from 1 to {MAX_SIZE} px")
    if not _integer(seed) or seed < 0:
        raise CorruptSample("seed", "out of range", f"{seed!r}, expected a non-negative integer")
    if not isinstance(record["params"], dict):
        raise CorruptSample("params", "not a map", f"a {type(record['params']).__name__}")
    geometry = get_shape(shape)
    mask_bytes = (size * size + 7) // 8
    lengths = {"keypoints": geometry.num_keypoints * 2 * np.dtype(KEYPOINT_DTYPE).itemsize,
               "noisy": mask_bytes, "clean": mask_bytes}
    for key, length in lengths.items():
        value = record[key]
        if not isinstance(value, bytes):
            raise CorruptSample(key, "not bytes", f"a {type(value).__name__}")
        if len(value) != length:
            raise CorruptSample(key, "wrong length", f"{len(value)} bytes, expected {length} for {size} px {shape}")
    _check_keypoints(np.frombuffer(record["keypoints"], KEYPOINT_DTYPE), size)
    _check_ratios(geometry, record["ratios"])


def _check_keypoints(keypoints: np.ndarray, size: int) -> None:
    reach = KEYPOINT_REACH * size
    low, high = -0.5 - reach, size - 0.5 + reach
    if low <= keypoints.min() and keypoints.max() <= high:  # False for a NaN too
        return
    if not np.isfinite(keypoints).all():
        bad = int(np.flatnonzero(~np.isfinite(keypoints))[0])
        raise CorruptSample("keypoints", "not finite", f"keypoint {bad // 2} {'xy'[bad % 2]} is {keypoints[bad]}")
    bad = int(np.flatnonzero((keypoints < low) | (keypoints > high))[0])
    raise CorruptSample("keypoints", "out of range",
                        f"keypoint {bad // 2} {'xy'[bad % 2]} is {keypoints[bad]:g} px, expected {low:g} to {high:g} "
                        f"for a {size} px image")


def _check_ratios(geometry, ratios) -> None:
    parts = [ratios] if len(geometry.parts) == 1 else None
    if parts is None:
        if not isinstance(ratios, dict) or set(ratios) != set(geometry.part_names):
            found = sorted(map(str, ratios)) if isinstance(ratios, dict) else type(ratios).__name__
            raise CorruptSample("ratios", "malformed", f"{found}, expected a map of {list(geometry.part_names)}")
        parts = [ratios[p] for p in geometry.part_names]
    low, high = RATIO_RANGE
    for part in parts:
        if not isinstance(part, dict) or set(part) != set(RATIO_KEYS):
            found = sorted(map(str, part)) if isinstance(part, dict) else type(part).__name__
            raise CorruptSample("ratios", "malformed", f"{found}, expected a map of {list(RATIO_KEYS)}")
        for key, value in part.items():
            if not _number(value):
                raise CorruptSample("ratios", "not a number", f"{key} is {value!r}")
            if not low <= value <= high:  # NaN fails the comparison too
                fault = "out of range" if math.isfinite(value) else "not finite"
                raise CorruptSample("ratios", fault, f"{key} is {value!r}, expected {low:g} to {high:g}")


def _integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def decode(data: bytes) -> Sample:
    """Bytes -> Sample. Raises ValueError for corrupt bytes or another format version."""
    return from_record(decode_record(data))


def from_record(r: dict) -> Sample:
    """A record of `decode_record` -> Sample: masks unpacked, keypoints (N, 2) float64."""
    n = get_shape(r["shape"]).num_keypoints
    return Sample(
        shape=r["shape"],
        size=r["size"],
        seed=r["seed"],
        keypoints=np.frombuffer(r["keypoints"], KEYPOINT_DTYPE).reshape(n, 2).copy(),
        ratios=r["ratios"],
        noisy=unpack_mask(r["noisy"], r["size"]),
        clean=unpack_mask(r["clean"], r["size"]),
        params=r["params"],
    )


@dataclass(frozen=True, slots=True, eq=False)
class PackedSample:
    """A sample as a batch is made of it: read and checked once (`decode_packed`), its masks still
    packed (`pack_mask`'s bytes: what a batch copies, 8x less than the pixels), its keypoints
    (N, 2) float64 px. `record` is what was read, for the rest of the sample (`unpacked`)."""

    shape: str
    size: int
    keypoints: np.ndarray  # (N, 2) float64 px: the sample's own, or the model's once framed
    ratios: np.ndarray  # (R,) float64: the shape's ratio vector (shared.shapes.Shape.ratio_vector)
    noisy: bytes
    clean: bytes
    record: dict
    checksum: int  # the payload's checksum as read (the one written, where checked): what a trainer's ledger keeps

    def noisy_mask(self) -> np.ndarray:
        """The noisy mask's (size, size) uint8 0/1 pixels."""
        return unpack_mask(self.noisy, self.size).view(np.uint8)

    def unpacked(self) -> Sample:
        """The whole sample as read: masks unpacked, keypoints in the sample's own px."""
        return from_record(self.record)


def decode_packed(data: bytes, verify: bool = True) -> PackedSample:
    """Bytes -> PackedSample, every field checked once (`decode_record`). Raises ValueError."""
    record, written = decode_checked(data, verify)
    geometry = get_shape(record["shape"])
    keypoints = np.frombuffer(record["keypoints"], KEYPOINT_DTYPE).reshape(geometry.num_keypoints, 2)
    return PackedSample(record["shape"], record["size"], keypoints, geometry.ratio_vector(record["ratios"]),
                        record["noisy"], record["clean"], record, written)


def packed_rows(samples: list[PackedSample], key: str, size: int) -> np.ndarray:
    """(B, ceil(size^2 / 8)) uint8: each sample's `key` mask ("noisy" or "clean") packed at `size`
    px, a smaller one padded with background below and right."""
    if all(s.size == size for s in samples):  # the usual batch: the bytes as read, joined
        # bytearray: a writable buffer, so torch.from_numpy can share it without a warning
        return np.frombuffer(bytearray().join(getattr(s, key) for s in samples), np.uint8).reshape(len(samples), -1)
    canvas = np.zeros((len(samples), size, size), np.uint8)
    for canvas_row, s in zip(canvas, samples):
        canvas_row[: s.size, : s.size] = unpack_mask(getattr(s, key), s.size)
    return np.packbits(canvas.reshape(len(samples), -1), axis=1, bitorder=BIT_ORDER)


def unpack_rows(packed: np.ndarray, count: int) -> np.ndarray:
    """(..., n) uint8 packed bits (`pack_mask`'s order) -> (..., count) uint8 0/1 along the last axis."""
    return np.unpackbits(packed, axis=-1, count=count, bitorder=BIT_ORDER)


def collate(samples: list[PackedSample], unpack: bool = True) -> dict[str, np.ndarray]:
    """Samples of one shape and size (`decode_packed`) -> batched arrays.

    `noisy`/`clean` are (B, H, W) uint8 0/1 when `unpack`, else the packed bits
    (B, H*W/8): a trainer can ship packed bits to its device and unpack there,
    8x less to copy. `keypoints` is (B, N, 2) float32, `ratios` (B, R) float32.
    """
    if not samples:
        raise ValueError("cannot collate an empty batch")
    shape, size = samples[0].shape, samples[0].size
    for s in samples:
        if s.shape != shape or s.size != size:
            raise ValueError(f"mixed batch: {s.shape} {s.size}px among {shape} {size}px samples")
    batch = {}
    if unpack and size * size % 8 == 0:
        # Both masks of the whole batch in one flat unpack into one array (two views): no
        # per-row padding to cut, and one large allocation rather than two, which glibc
        # would hand back to the kernel and fault in again, page by page, every batch
        # (ten times slower on this VM).
        packed = b"".join([s.noisy for s in samples] + [s.clean for s in samples])
        both = np.unpackbits(np.frombuffer(packed, np.uint8), bitorder=BIT_ORDER).reshape(2, len(samples), size, size)
        batch["noisy"], batch["clean"] = both[0], both[1]
    else:
        for key in ("noisy", "clean"):
            packed = packed_rows(samples, key, size)
            batch[key] = unpack_rows(packed, size * size).reshape(-1, size, size) if unpack else packed
    batch["keypoints"] = np.stack([s.keypoints for s in samples]).astype(np.float32)
    batch["ratios"] = np.stack([s.ratios for s in samples]).astype(np.float32)
    return batch
