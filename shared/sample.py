"""The training sample and its versioned byte format.

This module is the only code that turns samples into bytes and back (STYLE.md).
A sample is one msgpack map. Masks are bit-packed (`np.packbits`, row-major,
BIT_ORDER within a byte), keypoints are little-endian float64, so a 256x256
sample is about 17 KB. Heat maps are not stored: they are a function of the
keypoints and the trainer renders them on its device, where it also unpacks the
masks (in torch, by BIT_SHIFTS: the bit order is stated here and nowhere else).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import msgpack
import numpy as np

from shared.shapes import get_shape

FORMAT = "cuboid-fit/sample"
VERSION = 1
KEYPOINT_DTYPE = "<f8"  # little-endian float64, (N, 2) px row-major
BIT_ORDER = "big"  # np.packbits' default: a byte's first pixel is its most significant bit
# The right shift that brings each of a byte's 8 pixels, first pixel first, down to bit 0:
# for unpacking without numpy (the trainer unpacks a batch on its device, in torch).
BIT_SHIFTS = (7, 6, 5, 4, 3, 2, 1, 0) if BIT_ORDER == "big" else (0, 1, 2, 3, 4, 5, 6, 7)


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
    """A boolean mask as the paper's float32 +1 (object) / -1 (background)."""
    return np.where(mask, np.float32(1), np.float32(-1))


def pack_mask(mask: np.ndarray) -> bytes:
    """A (size, size) bool mask -> ceil(size^2 / 8) bytes, row-major, BIT_ORDER within a byte."""
    return np.packbits(mask, bitorder=BIT_ORDER).tobytes()


def unpack_mask(packed: bytes, size: int) -> np.ndarray:
    """`pack_mask`'s bytes -> the (size, size) bool mask."""
    bits = np.unpackbits(np.frombuffer(packed, np.uint8), count=size * size, bitorder=BIT_ORDER)
    return bits.reshape(size, size).view(bool)


def encode(sample: Sample) -> bytes:
    """Sample -> bytes."""
    return msgpack.packb(to_record(sample), use_bin_type=True)


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
    return {
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


def decode_record(data: bytes) -> dict:
    """Bytes -> the raw record, checked for format and version, masks still packed.

    Raises ValueError naming what was found and what was expected.
    """
    try:
        record = msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack raises several unrelated types for bad bytes
        raise ValueError(f"corrupt sample: not a msgpack map ({type(exc).__name__}: {exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        found = record.get("format") if isinstance(record, dict) else type(record).__name__
        raise ValueError(f"not a cuboid-fit sample: format {found!r}, expected {FORMAT!r}")
    if record.get("version") != VERSION:
        raise ValueError(
            f"sample format version {record.get('version')!r} is not supported: expected {VERSION}"
        )
    _check_lengths(record)
    return record


def _check_lengths(record: dict) -> None:
    try:
        n = get_shape(record["shape"]).num_keypoints
        size = int(record["size"])
        mask_bytes = (size * size + 7) // 8
        expected = {"keypoints": n * 2 * np.dtype(KEYPOINT_DTYPE).itemsize, "noisy": mask_bytes, "clean": mask_bytes}
        for key, length in expected.items():
            if len(record[key]) != length:
                raise ValueError(f"corrupt sample: {key} has {len(record[key])} bytes, expected {length}")
    except (KeyError, TypeError) as exc:
        raise ValueError(f"corrupt sample: missing or malformed field {exc}") from None


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


def collate(records: list[dict], unpack: bool = True) -> dict[str, np.ndarray]:
    """Decoded records of one shape and size -> batched arrays.

    `noisy`/`clean` are (B, H, W) uint8 0/1 when `unpack`, else the packed bits
    (B, H*W/8): a trainer can ship packed bits to its device and unpack there,
    8x less to copy. `keypoints` is (B, N, 2) float32, `ratios` (B, R) float32.
    """
    if not records:
        raise ValueError("cannot collate an empty batch")
    shape, size = records[0]["shape"], records[0]["size"]
    geometry = get_shape(shape)
    for r in records:
        if r["shape"] != shape or r["size"] != size:
            raise ValueError(f"mixed batch: {r['shape']} {r['size']}px among {shape} {size}px samples")
    batch = {}
    if unpack and size * size % 8 == 0:
        # Both masks of the whole batch in one flat unpack into one array (two views): no
        # per-row padding to cut, and one large allocation rather than two, which glibc
        # would hand back to the kernel and fault in again, page by page, every batch
        # (ten times slower on this VM).
        packed = b"".join([r["noisy"] for r in records] + [r["clean"] for r in records])
        both = np.unpackbits(np.frombuffer(packed, np.uint8), bitorder=BIT_ORDER).reshape(2, len(records), size, size)
        batch["noisy"], batch["clean"] = both[0], both[1]
    else:
        for key in ("noisy", "clean"):
            # bytearray: a writable buffer, so torch.from_numpy can share it without a warning
            packed = np.frombuffer(bytearray(b"".join([r[key] for r in records])), np.uint8).reshape(len(records), -1)
            batch[key] = (np.unpackbits(packed, axis=1, count=size * size, bitorder=BIT_ORDER).reshape(-1, size, size)
                          if unpack else packed)
    keypoints = np.frombuffer(b"".join(r["keypoints"] for r in records), KEYPOINT_DTYPE)
    batch["keypoints"] = keypoints.reshape(len(records), geometry.num_keypoints, 2).astype(np.float32)
    batch["ratios"] = np.stack([geometry.ratio_vector(r["ratios"]) for r in records]).astype(np.float32)
    return batch
