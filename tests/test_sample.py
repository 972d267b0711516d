"""The sample byte format: round trips, size, and clear errors for corrupt or foreign bytes."""
import msgpack
import numpy as np
import pytest

from shared.sample import (BIT_SHIFTS, VERSION, collate, decode, decode_record, encode, from_record, pack_mask,
                           signed, to_record, unpack_mask)
from tests.conftest import build_sample


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_round_trip_keeps_every_field(shape, library):
    sample = build_sample(3, shape, library=library)
    back = decode(encode(sample))
    assert back.shape == sample.shape and back.size == sample.size and back.seed == sample.seed
    assert (back.noisy == sample.noisy).all() and (back.clean == sample.clean).all()
    assert np.array_equal(back.keypoints, sample.keypoints)  # float64: exact
    assert back.ratios == sample.ratios and back.params == sample.params
    assert back == sample


def test_the_record_is_what_decode_record_reads_and_from_record_gives_the_sample_back(library):
    sample = build_sample(5, "twobox", library=library)
    record = to_record(sample)
    assert record == decode_record(encode(sample))
    assert from_record(record) == sample


@pytest.mark.parametrize("size", [8, 33, 48])  # 33: 1089 bits, the last byte padded with zeros
def test_mask_packing_round_trips_and_is_numpys_packbits(size):
    mask = np.random.default_rng(size).random((size, size)) < 0.3
    packed = pack_mask(mask)
    assert len(packed) == (size * size + 7) // 8 and packed == np.packbits(mask).tobytes()  # docs/contract.md
    assert np.array_equal(unpack_mask(packed, size), mask) and unpack_mask(packed, size).dtype == bool


def test_bit_shifts_bring_each_pixel_of_a_byte_down_in_pixel_order():
    # BIT_SHIFTS is how code without numpy (the trainer's torch) reads shared's bit order.
    for pixel in range(8):
        mask = np.zeros((4, 4), bool)
        mask.flat[pixel] = True
        first = pack_mask(mask)[0]
        assert [(first >> shift) & 1 for shift in BIT_SHIFTS] == [int(p == pixel) for p in range(8)]


def test_a_256_px_sample_stays_under_20_kb(library):
    data = encode(build_sample(1, "twobox", size=256, library=library))
    assert len(data) <= 20 * 1024


def test_signed_masks_are_plus_minus_one():
    mask = np.array([[True, False]])
    assert signed(mask).tolist() == [[1.0, -1.0]] and signed(mask).dtype == np.float32


def test_version_mismatch_names_both_versions(library):
    record = msgpack.unpackb(encode(build_sample(0, library=library)))
    record["version"] = VERSION + 1
    with pytest.raises(ValueError, match=f"version {VERSION + 1}.*expected {VERSION}"):
        decode(msgpack.packb(record, use_bin_type=True))


@pytest.mark.parametrize("damage", [
    lambda b: b[: len(b) // 2],  # truncated
    lambda b: b"\x00" * 40,  # zeros
    lambda b: b"",  # empty
    lambda b: b"PNG not a sample",  # foreign
    lambda b: msgpack.packb({"format": "something/else"}),
    lambda b: msgpack.packb([1, 2, 3]),
])
def test_corrupt_bytes_raise_value_error(damage, library):
    with pytest.raises(ValueError):
        decode(damage(encode(build_sample(0, library=library))))


def test_short_mask_field_is_corrupt(library):
    record = msgpack.unpackb(encode(build_sample(0, library=library)))
    record["clean"] = record["clean"][:-1]
    with pytest.raises(ValueError, match="clean has"):
        decode_record(msgpack.packb(record, use_bin_type=True))


def test_encode_refuses_wrong_keypoint_count(library):
    from dataclasses import replace

    with pytest.raises(ValueError, match=r"expected \(8, 2\)"):
        encode(replace(build_sample(0, library=library), keypoints=np.zeros((14, 2))))


def test_collate_batches_records_in_order(library):
    samples = [build_sample(i, library=library) for i in range(4)]
    batch = collate([decode_record(encode(s)) for s in samples])
    assert batch["noisy"].shape == (4, 48, 48) and batch["noisy"].dtype == np.uint8
    assert batch["keypoints"].shape == (4, 8, 2) and batch["ratios"].shape == (4, 2)
    for i, s in enumerate(samples):
        assert (batch["clean"][i] == s.clean).all() and np.allclose(batch["keypoints"][i], s.keypoints)
    packed = collate([decode_record(encode(s)) for s in samples], unpack=False)
    assert packed["noisy"].shape == (4, 48 * 48 // 8)
    assert (np.unpackbits(packed["noisy"], axis=1).reshape(4, 48, 48) == batch["noisy"]).all()


def test_collate_refuses_mixed_shapes(library):
    records = [decode_record(encode(build_sample(0, s, library=library))) for s in ("box", "twobox")]
    with pytest.raises(ValueError, match="mixed batch"):
        collate(records)
