"""The sample byte format: round trips, size, and clear errors for corrupt or foreign bytes."""
import zlib

import msgpack
import numpy as np
import pytest

from shared.sample import (BIT_SHIFTS, VERSION, DamagedSample, collate, decode, decode_packed, decode_record, encode, from_record,
                           pack_mask, pack_record, packed_rows, signed, to_record, unpack_mask)
from shared.shapes import get_shape
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
    record = to_record(build_sample(0, library=library))
    record["version"] = VERSION + 1
    with pytest.raises(ValueError, match=f"version {VERSION + 1}.*expected {VERSION}"):
        decode(pack_record(record))


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
    record = to_record(build_sample(0, library=library))
    record["clean"] = record["clean"][:-1]
    with pytest.raises(ValueError, match="clean: wrong length"):
        decode_record(pack_record(record))


def test_encode_refuses_wrong_keypoint_count(library):
    from dataclasses import replace

    with pytest.raises(ValueError, match=r"expected \(8, 2\)"):
        encode(replace(build_sample(0, library=library), keypoints=np.zeros((14, 2))))


def test_a_packed_sample_is_the_sample_read_once_its_masks_still_packed(library):
    for shape in ("box", "twobox"):
        sample = build_sample(3, shape, library=library)
        packed = decode_packed(encode(sample))
        assert packed.unpacked() == sample and (packed.shape, packed.size) == (sample.shape, sample.size)
        np.testing.assert_array_equal(packed.keypoints, sample.keypoints)
        np.testing.assert_array_equal(packed.ratios, get_shape(shape).ratio_vector(sample.ratios))
        assert packed.noisy == pack_mask(sample.noisy) and packed.clean == pack_mask(sample.clean)
        np.testing.assert_array_equal(packed.noisy_mask(), sample.noisy.astype(np.uint8))


def test_packed_rows_pad_a_smaller_sample_with_background(library):
    small, large = build_sample(0, size=24, library=library), build_sample(1, size=40, library=library)
    rows = packed_rows([decode_packed(encode(s)) for s in (small, large)], "clean", 40)
    unpacked = np.unpackbits(rows, axis=1, count=40 * 40).reshape(2, 40, 40).astype(bool)
    np.testing.assert_array_equal(unpacked[1], large.clean)
    np.testing.assert_array_equal(unpacked[0, :24, :24], small.clean)
    assert not unpacked[0, 24:].any() and not unpacked[0, :, 24:].any()


def test_collate_batches_records_in_order(library):
    samples = [build_sample(i, library=library) for i in range(4)]
    batch = collate([decode_packed(encode(s)) for s in samples])
    assert batch["noisy"].shape == (4, 48, 48) and batch["noisy"].dtype == np.uint8
    assert batch["keypoints"].shape == (4, 8, 2) and batch["ratios"].shape == (4, 2)
    for i, s in enumerate(samples):
        assert (batch["clean"][i] == s.clean).all() and np.allclose(batch["keypoints"][i], s.keypoints)
    packed = collate([decode_packed(encode(s)) for s in samples], unpack=False)
    assert packed["noisy"].shape == (4, 48 * 48 // 8)
    assert (np.unpackbits(packed["noisy"], axis=1).reshape(4, 48, 48) == batch["noisy"]).all()


def test_collate_refuses_mixed_shapes(library):
    records = [decode_packed(encode(build_sample(0, s, library=library))) for s in ("box", "twobox")]
    with pytest.raises(ValueError, match="mixed batch"):
        collate(records)


# --- every field checked: a well-formed sample with a bad value is corrupt, with a reason ---------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from shared.sample import KEYPOINT_REACH, MAX_SIZE, RATIO_RANGE, CorruptSample  # noqa: E402

INTS = st.integers(-2**63, 2**63 - 1)  # what msgpack packs
NON_FINITE = st.sampled_from([float("nan"), float("inf"), float("-inf")])
NOT_INTEGERS = st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True), st.text(max_size=4),
                         st.lists(INTS, max_size=2), st.binary(max_size=4))
NOT_BYTES = st.one_of(st.none(), INTS, st.floats(), st.text(max_size=8), st.lists(INTS, max_size=2))
NOT_NUMBERS = st.one_of(st.none(), st.booleans(), st.text(max_size=4), st.lists(st.floats(), max_size=2),
                        st.dictionaries(st.text(max_size=2), INTS, max_size=1))
PROPERTY = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def a_record(library, shape: str = "box") -> dict:
    return to_record(build_sample(0, shape, library=library))


def refused(record: dict, field: str) -> CorruptSample:
    """decode_record refuses the record, naming `field` in the message and the census reason."""
    with pytest.raises(CorruptSample) as caught:
        decode_record(pack_record(record))
    assert caught.value.reason.startswith(f"{field}: ") and str(caught.value).startswith(f"corrupt sample: {field}: ")
    assert "\n" not in str(caught.value)
    return caught.value


def out_of_range_keypoint(size: int):
    reach = KEYPOINT_REACH * size
    return st.one_of(st.floats(max_value=-0.5 - reach - 1e-6, allow_nan=False, allow_infinity=False),
                     st.floats(min_value=size - 0.5 + reach + 1e-6, allow_nan=False, allow_infinity=False))


@PROPERTY
@given(shape=st.sampled_from(["box", "twobox"]), index=st.integers(0, 27), data=st.data())
def test_a_non_finite_or_out_of_range_keypoint_is_corrupt(library, shape, index, data):
    record = a_record(library, shape)
    keypoints = np.frombuffer(record["keypoints"], "<f8").copy()
    bad = data.draw(st.one_of(NON_FINITE, out_of_range_keypoint(record["size"])))
    keypoints[index % keypoints.size] = bad
    record["keypoints"] = keypoints.tobytes()
    fault = refused(record, "keypoints").reason
    assert fault == ("keypoints: not finite" if not np.isfinite(bad) else "keypoints: out of range")


@PROPERTY
@given(shape=st.sampled_from(["box", "twobox"]), which=st.integers(0, 3), data=st.data())
def test_a_non_finite_out_of_range_or_non_numeric_ratio_is_corrupt(library, shape, which, data):
    record = a_record(library, shape)
    part = record["ratios"] if shape == "box" else record["ratios"][("right", "left")[which // 2]]
    key = ("depth_height", "width_height")[which % 2]
    low, high = RATIO_RANGE
    part[key] = data.draw(st.one_of(NON_FINITE, st.floats(max_value=low, exclude_max=True),
                                    st.floats(min_value=high, exclude_min=True, allow_infinity=False),
                                    st.integers(-2**63, 0), NOT_NUMBERS))
    refused(record, "ratios")


@PROPERTY
@given(shape=st.sampled_from(["box", "twobox"]), ratios=st.one_of(
    NOT_NUMBERS, st.floats(), st.dictionaries(st.sampled_from(["depth_height", "width_height", "left", "right", "x"]),
                                               st.floats(1, 2), max_size=3)))
def test_a_malformed_ratio_record_is_corrupt(library, shape, ratios):
    record = a_record(library, shape)
    if isinstance(ratios, dict) and shape == "box" and set(ratios) == {"depth_height", "width_height"}:
        ratios["x"] = 1.0  # an extra key is malformed too
    record["ratios"] = ratios
    refused(record, "ratios")


@PROPERTY
@given(field=st.sampled_from(["noisy", "clean", "keypoints"]), data=st.data())
def test_a_mask_or_keypoint_field_of_the_wrong_size_or_type_is_corrupt(library, field, data):
    record = a_record(library)
    length = len(record[field])
    record[field] = data.draw(st.one_of(NOT_BYTES, st.binary(max_size=2 * length).filter(lambda b: len(b) != length)))
    refused(record, field)


@PROPERTY
@given(field=st.sampled_from(["size", "seed"]), data=st.data())
def test_a_size_or_seed_out_of_range_or_not_an_integer_is_corrupt(library, field, data):
    record = a_record(library)
    low, high = (1, MAX_SIZE) if field == "size" else (0, None)
    out = st.integers(max_value=low - 1) if high is None else st.one_of(st.integers(max_value=low - 1),
                                                                         st.integers(min_value=high + 1))
    record[field] = data.draw(st.one_of(out.filter(lambda v: -2**63 <= v < 2**63), NOT_INTEGERS))
    refused(record, field)


@PROPERTY
@given(field=st.sampled_from(["shape", "size", "seed", "keypoints", "ratios", "noisy", "clean", "params"]),
       value=st.one_of(st.none(), INTS, st.text(max_size=6), st.lists(INTS, max_size=2)),
       drop=st.booleans())
def test_a_missing_or_mistyped_field_is_corrupt(library, field, value, drop):
    record = a_record(library)
    if drop:
        del record[field]
    else:
        if field == "shape" and value in ("box", "twobox"):
            value = "cone"
        elif field in ("size", "seed") and isinstance(value, int):
            value = str(value)  # "64" is no size
        record[field] = value
    refused(record, field)


@PROPERTY
@given(shape=st.sampled_from(["box", "twobox"]), data=st.data())
def test_any_finite_sample_in_range_round_trips(library, shape, data):
    """The reader refuses only what is out of bounds: anything inside them decodes unchanged."""
    record = a_record(library, shape)
    size, reach = record["size"], KEYPOINT_REACH * record["size"]
    n = len(record["keypoints"]) // 8
    keypoints = data.draw(st.lists(st.floats(-0.5 - reach, size - 0.5 + reach), min_size=n, max_size=n))
    record["keypoints"] = np.array(keypoints, "<f8").tobytes()
    ratio = st.floats(*RATIO_RANGE)
    parts = [record["ratios"]] if shape == "box" else list(record["ratios"].values())
    for part in parts:
        for key in part:
            part[key] = data.draw(ratio)
    assert decode_record(pack_record(record)) == record


def test_encode_refuses_a_sample_its_readers_would_refuse(library):
    from dataclasses import replace

    sample = build_sample(0, library=library)
    keypoints = sample.keypoints.copy()
    keypoints[3, 1] = np.nan
    with pytest.raises(CorruptSample, match=r"^corrupt sample: keypoints: not finite \(keypoint 3 y is nan\)$"):
        encode(replace(sample, keypoints=keypoints))
    with pytest.raises(CorruptSample, match="ratios: out of range"):
        encode(replace(sample, ratios={"depth_height": 0.0, "width_height": 1.0}))


def flipped(data: bytes, bit: int) -> bytes:
    """`data` with one bit flipped (bit 0 is the first byte's most significant)."""
    damaged = bytearray(data)
    damaged[bit // 8] ^= 0x80 >> (bit % 8)
    return bytes(damaged)


def test_every_single_flipped_bit_of_a_sample_is_refused(library):
    # A 16 px sample is a few hundred bytes: every one of its bits, flipped alone, is caught,
    # most by the payload's checksum (DamagedSample), the rest (the map's own bytes) as corrupt.
    data = encode(build_sample(2, size=16, library=library))
    damaged = 0
    for bit in range(len(data) * 8):
        with pytest.raises(ValueError) as refused:
            decode_record(flipped(data, bit))
        damaged += isinstance(refused.value, DamagedSample)
    assert damaged > len(data) * 8 * 0.8  # the payload is most of the file


ENCODED: dict[tuple, bytes] = {}  # the property's samples, drawn once across its examples


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 3), shape=st.sampled_from(["box", "twobox"]), size=st.sampled_from([17, 64, 256]),
       data=st.data())
def test_any_single_flipped_bit_of_the_payload_is_a_checksum_mismatch(library, seed, shape, size, data):
    key = (seed, shape, size)
    if key not in ENCODED:
        ENCODED[key] = encode(build_sample(seed, shape, size=size, library=library))
    written = ENCODED[key]
    payload = msgpack.unpackb(written)["payload"]
    start = written.rindex(payload)  # a msgpack bin's bytes lie in the file as they are
    bit = data.draw(st.integers(0, len(payload) * 8 - 1))
    with pytest.raises(DamagedSample) as refused:
        decode_record(flipped(written, start * 8 + bit))
    assert refused.value.reason == "checksum: mismatch" and "\n" not in str(refused.value)


def test_a_flipped_bit_in_a_mask_is_a_checksum_mismatch_with_its_own_reason(library):
    data = encode(build_sample(2, library=library))
    with pytest.raises(DamagedSample, match="corrupt sample: checksum: mismatch") as refused:
        decode(flipped(data, len(data) * 4))  # the middle of the file: the noisy mask's bits
    assert refused.value.reason == "checksum: mismatch"
    assert decode_record(flipped(data, len(data) * 4), verify=False)["shape"] == "box"  # unchecked, it would pass


def version_1_bytes(record: dict) -> bytes:
    """What version 1's encoder wrote: the fields in the one map, no checksum."""
    return msgpack.packb({**record, "version": 1}, use_bin_type=True)


def version_2_bytes(record: dict) -> bytes:
    """What version 2's encoder wrote: the payload (the fields but format and version) with zlib's CRC-32."""
    payload = msgpack.packb({k: v for k, v in record.items() if k not in ("format", "version")}, use_bin_type=True)
    return msgpack.packb({"format": record["format"], "version": 2, "crc32": zlib.crc32(payload), "payload": payload},
                         use_bin_type=True)


@pytest.mark.parametrize("old, why", [
    (version_1_bytes, r"\(version 1 carried no checksum: draw the spool afresh\)"),
    (version_2_bytes, r"\(version 2's checksum was a CRC-32: draw the spool afresh\)"),
])
def test_an_older_version_is_refused_in_one_line_saying_why(library, old, why):
    data = old(to_record(build_sample(0, library=library)))
    version = msgpack.unpackb(data)["version"]
    with pytest.raises(ValueError, match=rf"^sample format version {version} is not supported: expected {VERSION} {why}$") as refused:
        decode_record(data)
    assert not isinstance(refused.value, DamagedSample) and "\n" not in str(refused.value)  # old, not damaged
