"""The trainer's side of the spool: SpoolBatches, EpochSampler, make_loader, FreshnessMeter, SpoolCensus,
and prepare_batch (packed masks unpacked, reframed and heat maps rendered on the device)."""
from __future__ import annotations

import os
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from cuboidgen.config import PAPER, PAPER_CLEAN, STREET
from cuboidtrain.models.codec import render_heatmaps
from cuboidtrain.data.device_framing import frame_masks, unpack_masks
from cuboidtrain.data.freshness import FreshnessMeter
from cuboidtrain.data.loader import SKIP_REASONS, SpoolBatches, make_loader
from cuboidtrain.data.prepare import prepare_batch
from cuboidtrain.data.sampler import EpochPosition, EpochSampler, LoaderState
from cuboidtrain.data.census import SpoolCensus, parse_name, published_between
from shared.sample import VERSION, encode, pack_mask, pack_record, signed, to_record, unpack_mask
from shared.shapes import get_shape
from shared.spool import SpoolWriter, enumerate_spool
from tests.conftest import SIZE, build_sample, fill_spool


def sample_name(seq: int = 1, t_ns: int | None = None) -> str:
    """A name a writer could have published (so the spool lists it)."""
    t_ns = time.time_ns() if t_ns is None else t_ns
    return f"{t_ns:019d}-testhost-1-abcdef-{seq:09d}.cub"


def publish(spool: Path, samples, limit: int = 0) -> list[str]:
    with SpoolWriter(spool, limit=limit) as writer:
        return [writer.publish(encode(s)) for s in samples]


def no_skips(**counts) -> dict:
    return {**dict.fromkeys(SKIP_REASONS, 0), **counts}


def consume(sampler: EpochSampler, batches: int | None = None) -> list[list[str]]:
    """Iterate one epoch the way the trainer does: position advances with every batch taken."""
    taken = []
    for names in sampler:
        taken.append(names)
        sampler.advance()
        if batches is not None and len(taken) == batches:
            break
    return taken


# ---- SpoolBatches ---------------------------------------------------------------------


def test_spool_batches_returns_packed_masks_and_keeps_names(tmp_path):
    names = fill_spool(tmp_path, 3)
    dataset = SpoolBatches(tmp_path, "box", SIZE)
    assert len(dataset) == 3
    batch = dataset[[names[2], names[0]]]
    assert batch.names == [names[2], names[0]]
    assert batch.skipped == no_skips() and batch.vanished == []
    assert batch.noisy.shape == batch.clean.shape == (2, SIZE * SIZE // 8)
    assert batch.noisy.dtype == torch.uint8
    assert batch.keypoints.shape == (2, 8, 2) and batch.keypoints.dtype == torch.float32
    assert batch.ratios.shape == (2, 2)
    for row, seed in enumerate([2, 0]):  # fill_spool publishes seeds 0.. in order
        sample = build_sample(seed)
        assert np.array_equal(batch.noisy[row].numpy(), np.packbits(sample.noisy))
        assert np.array_equal(batch.clean[row].numpy(), np.packbits(sample.clean))
        assert np.allclose(batch.keypoints[row].numpy(), sample.keypoints)
        assert np.allclose(batch.ratios[row].numpy(), get_shape("box").ratio_vector(sample.ratios))


def test_a_name_evicted_after_listing_is_skipped_as_vanished(tmp_path):
    names = fill_spool(tmp_path, 3)
    listed = enumerate_spool(tmp_path)
    os.unlink(tmp_path / names[1])
    batch = SpoolBatches(tmp_path, "box", SIZE)[listed]
    assert batch.names == [names[0], names[2]]
    assert batch.skipped == no_skips(vanished=1) and batch.vanished == [names[1]]  # the census's input
    assert batch.noisy.shape[0] == 2


def good_record() -> dict:
    return to_record(build_sample(0))


@pytest.mark.parametrize("bad_bytes", [
    lambda: np.random.default_rng(0).bytes(300),  # garbage
    lambda: b"",  # an empty file
    lambda: encode(build_sample(0))[:-40],  # truncated
    lambda: pack_record({**good_record(), "version": VERSION + 1}),  # a future format
    lambda: pack_record({**good_record(), "keypoints": b"\x00" * 8}),  # a short field
    lambda: pack_record({**good_record(), "ratios": "none"}),  # a malformed ratio record
    lambda: pack_record({**good_record(), "ratios": {"depth_height": 1.0}}),  # one missing
], ids=["garbage", "empty", "truncated", "future_version", "short_field", "ratios_not_a_map", "ratio_missing"])
def test_bad_bytes_under_a_sample_name_are_skipped_as_corrupt(tmp_path, bad_bytes):
    names = fill_spool(tmp_path, 2)
    bad = sample_name()
    (tmp_path / bad).write_bytes(bad_bytes())
    batch = SpoolBatches(tmp_path, "box", SIZE)[[names[0], bad, names[1]]]
    assert batch.names == names
    assert batch.skipped == no_skips(corrupt=1)
    assert batch.keypoints.shape[0] == 2


def test_other_shapes_and_sizes_are_skipped_and_counted(tmp_path):
    boxes = publish(tmp_path, [build_sample(0), build_sample(1)])
    twoboxes = publish(tmp_path, [build_sample(2, "twobox")])
    small = publish(tmp_path, [build_sample(3, size=32), build_sample(4, size=32)])
    everything = boxes + twoboxes + small
    batch = SpoolBatches(tmp_path, "box", SIZE)[everything]
    assert batch.names == boxes
    assert batch.skipped == no_skips(other_shape=1, other_size=2)
    batch = SpoolBatches(tmp_path, "twobox", SIZE)[everything]
    assert batch.names == twoboxes and batch.keypoints.shape == (1, 14, 2) and batch.ratios.shape == (1, 4)
    assert batch.skipped == no_skips(other_shape=4)  # the 32 px samples are boxes
    batch = SpoolBatches(tmp_path, "box", 32)[everything]
    assert batch.names == small
    assert batch.skipped == no_skips(other_shape=1, other_size=2)


# ---- reframing: train as you infer ------------------------------------------------------
# The loader finds each sample's building and framing; prepare_batch carries the masks onto the
# model's input on the device (frame_masks). Today's framing, infer's own (Fitter._fit_parts), is
# the reference: fit.masks' frame of the noisy mask's silhouette, the clean mask warped alike.

CPU = torch.device("cpu")
MAX_DIFFERING = 0.005  # issue 29: at most 0.5% of a mask's pixels may differ from today's framing


def todays_framing(sample, size: int):
    """(noisy, clean, keypoints) as the trainer framed a sample before issue 29, on the CPU."""
    from cuboidtrain.fit.masks import frame, silhouette, warp

    framed, framing = frame(silhouette(sample.noisy), size)
    return framed, warp(sample.clean, framing), framing.to_model(sample.keypoints)


def differing(prepared: torch.Tensor, mask: np.ndarray) -> float:
    """The share of pixels where a prepared (1, size, size) +1/-1 mask and a bool mask differ."""
    return float(((prepared[0] > 0).numpy() != mask).mean())


@pytest.mark.parametrize(("source", "size", "scene"), [(96, 32, PAPER), (128, 64, STREET), (96, 48, PAPER_CLEAN),
                                                       (40, 64, PAPER), (64, 64, STREET)])
def test_a_reframed_batch_prepares_to_what_infer_frames_from_its_noisy_mask(tmp_path, source, size, scene):
    # shrinking (a Gaussian, then bilinear), enlarging (bilinear only) and nearly the identity
    samples = [build_sample(seed, size=source, scene=scene) for seed in range(12)]
    sample_of = dict(zip(publish(tmp_path, samples), samples))
    batch = SpoolBatches(tmp_path, "box", size, reframe="always")[enumerate_spool(tmp_path)]
    assert len(batch.names) + batch.skipped["cut_off"] == len(samples) and len(batch.names) >= 8
    assert batch.source == source and batch.noisy.shape == (len(batch.names), source * source // 8)
    x = prepare_batch(batch, CPU, 1.0, size)
    assert x.x1.shape == x.x2.shape == (len(batch.names), 1, size, size)
    worst = 0.0
    for row, name in enumerate(batch.names):
        noisy, clean, keypoints = todays_framing(sample_of[name], size)
        np.testing.assert_allclose(x.x4[row].numpy(), keypoints, atol=1e-4)  # the same crop, to 1e-4 px
        worst = max(worst, differing(x.x1[row], noisy), differing(x.x2[row], clean))
    assert worst <= MAX_DIFFERING
    assert worst <= 0.001  # measured: 0 pixels in these batches (the same kernel, to float rounding)
    assert torch.equal(x.x3, render_heatmaps(x.x4, size, 1.0))


@pytest.mark.parametrize(("source", "size"), [(128, 64), (96, 48)])
def test_a_grey_batch_prepares_to_what_infer_frames_for_a_grey_model(tmp_path, source, size):
    from cuboidtrain.fit.masks import frame, silhouette, warp

    samples = [build_sample(seed, size=source, scene=STREET if seed % 2 else PAPER) for seed in range(10)]
    sample_of = dict(zip(publish(tmp_path, samples), samples))
    batch = SpoolBatches(tmp_path, "box", size, reframe="always")[enumerate_spool(tmp_path)]
    grey, binary = prepare_batch(batch, CPU, 1.0, size, grey=True), prepare_batch(batch, CPU, 1.0, size)
    assert torch.equal(grey.x1 >= 0, binary.x1 > 0) and torch.equal(grey.x2 >= 0, binary.x2 > 0)
    assert ((grey.x1 > -1) & (grey.x1 < 1)).any()  # edge pixels between object and background
    for row, name in enumerate(batch.names):
        noisy, framing = frame(silhouette(sample_of[name].noisy), size, grey=True)
        np.testing.assert_allclose(grey.x1[row, 0].numpy(), noisy * 2 - 1, atol=2e-4)
        np.testing.assert_allclose(grey.x2[row, 0].numpy(), warp(sample_of[name].clean, framing, grey=True) * 2 - 1,
                                   atol=2e-4)


def test_a_grey_input_without_framings_is_refused(tmp_path):
    publish(tmp_path, [build_sample(seed, size=32) for seed in range(2)])
    batch = SpoolBatches(tmp_path, "box", 32, reframe="never")[enumerate_spool(tmp_path)]
    with pytest.raises(ValueError, match="a grey input needs the batch's framings"):
        prepare_batch(batch, CPU, 1.0, 32, grey=True)


def test_building_and_box_is_the_silhouette_of_fit_masks_with_its_bounding_box():
    import cv2

    from cuboidtrain.fit.masks import silhouette
    from cuboidtrain.data.reframing import building_and_box

    rng = np.random.default_rng(0)
    cases = [build_sample(seed, size=96).noisy for seed in range(20)]
    for trial in range(400):  # pieces in holes, dropped pieces with holes, pieces on the border
        side = int(rng.integers(3, 48))
        mask = rng.random((side, side)) < rng.uniform(0.05, 0.8)
        cases.append(cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) if trial % 2 else mask)
    for mask in cases:
        for share, least in ((0.01, 16), (0.2, 4)):
            want, found = silhouette(mask, share, least), building_and_box(mask.astype(np.uint8), share, least)
            assert (want is None) == (found is None)
            if want is not None:
                np.testing.assert_array_equal(found[0].astype(bool), want)
                assert found[1] == cv2.boundingRect(want.astype(np.uint8))


def test_a_batch_of_several_source_sizes_frames_each_sample_as_alone(tmp_path):
    samples = [build_sample(0, size=64), build_sample(1, size=96), build_sample(2, size=40)]
    publish(tmp_path, samples)
    names = enumerate_spool(tmp_path)
    together = prepare_batch(SpoolBatches(tmp_path, "box", 32, reframe="always")[names], CPU, 1.0, 32)
    for row, name in enumerate(names):
        alone = prepare_batch(SpoolBatches(tmp_path, "box", 32, reframe="always")[[name]], CPU, 1.0, 32)
        assert torch.equal(together.x1[row], alone.x1[0]) and torch.equal(together.x2[row], alone.x2[0])
        assert torch.equal(together.x4[row], alone.x4[0])


def test_the_identity_framing_gives_the_masks_back_bit_for_bit():
    rng = np.random.default_rng(3)
    masks = rng.random((2, 5, 40, 40)) < 0.5
    packed = [torch.from_numpy(np.packbits(m.reshape(5, -1), axis=1)) for m in masks]
    identity = torch.tensor([[1.0, 0.0, 0.0]] * 5, dtype=torch.float64)
    noisy, clean = frame_masks(*packed, identity, 40, 40)
    assert torch.equal(noisy[:, 0] > 0, torch.from_numpy(masks[0])) and torch.equal(clean[:, 0] > 0, torch.from_numpy(masks[1]))


@pytest.mark.parametrize("size", [24, 48, 64])
def test_the_columns_pass_by_chunks_equals_the_single_product(tmp_path, monkeypatch, size):
    # A CPU takes the columns chunk by chunk on the transposed rows' result (DENSE_MOST 0), a GPU
    # by one product up to 64 px: both are the same weights, summed in another order.
    from cuboidtrain.data import device_framing as data

    publish(tmp_path, [build_sample(seed, size=96, scene=STREET if seed % 2 else PAPER) for seed in range(10)])
    batch = SpoolBatches(tmp_path, "box", size, reframe="always")[enumerate_spool(tmp_path)]
    framed = {}
    for most in (0, 64):
        monkeypatch.setitem(data.DENSE_MOST, "cpu", most)
        framed[most] = frame_masks(batch.noisy, batch.clean, batch.framing, batch.source, size)
    for by_chunks, at_once in zip(framed[0], framed[64]):
        assert by_chunks.shape == at_once.shape == (len(batch.names), 1, size, size)
        assert (by_chunks != at_once).float().mean() <= 0.0005  # measured: none differ


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_gpu_frames_a_batch_as_the_cpu_does(tmp_path):
    publish(tmp_path, [build_sample(seed, size=128) for seed in range(8)])
    batch = SpoolBatches(tmp_path, "box", 64, reframe="always")[enumerate_spool(tmp_path)]
    on_cpu, on_gpu = prepare_batch(batch, CPU, 1.0, 64), prepare_batch(batch, torch.device("cuda"), 1.0, 64)
    for a, b in ((on_cpu.x1, on_gpu.x1), (on_cpu.x2, on_gpu.x2)):
        assert (a != b.cpu()).float().mean() <= 0.0005
    torch.testing.assert_close(on_cpu.x4, on_gpu.x4.cpu())


def test_reframing_keeps_the_clean_silhouettes_corners_on_its_keypoints(tmp_path):
    # Property: after reframing a clean sample, each keypoint still lies on the clean mask's hull.
    sample = build_sample(2, size=128, scene=PAPER_CLEAN)
    publish(tmp_path, [sample])
    x = prepare_batch(SpoolBatches(tmp_path, "box", 64, reframe="always")[enumerate_spool(tmp_path)], CPU, 1.0, 64)
    ys, xs = np.nonzero((x.x2[0, 0] > 0).numpy())
    kp = x.x4[0].numpy()
    assert xs.min() - 1 <= kp[:, 0].min() and kp[:, 0].max() <= xs.max() + 1
    assert ys.min() - 1 <= kp[:, 1].min() and kp[:, 1].max() <= ys.max() + 1


def test_reframe_modes_choose_which_samples_are_framed(tmp_path):
    small, large = build_sample(0, size=32), build_sample(1, size=64)
    publish(tmp_path, [small, large])
    names = enumerate_spool(tmp_path)
    never = SpoolBatches(tmp_path, "box", 32, reframe="never")[names]
    assert never.names == names[:1] and never.skipped == no_skips(other_size=1)
    assert never.framing is None  # the spool's own framing: the batch as before issue 29
    other = SpoolBatches(tmp_path, "box", 32, reframe="other-sizes")[names]
    assert other.names == names  # the 32 px sample as the generator framed it, the 64 px one reframed
    assert other.framing[0].tolist() == [1.0, 0.0, 0.0]
    prepared = prepare_batch(other, CPU, 1.0, 32)
    assert torch.equal(prepared.x1[0, 0] > 0, torch.from_numpy(small.noisy))
    np.testing.assert_allclose(prepared.x4[0].numpy(), small.keypoints, atol=1e-5)
    assert differing(prepared.x1[1], todays_framing(large, 32)[0]) <= MAX_DIFFERING
    always = prepare_batch(SpoolBatches(tmp_path, "box", 32, reframe="always")[names], CPU, 1.0, 32)
    assert not torch.equal(always.x1[0, 0] > 0, torch.from_numpy(small.noisy))  # framed again, 10% margin
    only_own = SpoolBatches(tmp_path, "box", 32, reframe="other-sizes")[names[:1]]
    assert only_own.framing is None  # nothing to frame: the plain batch
    with pytest.raises(ValueError, match="reframe 'sometimes'"):
        SpoolBatches(tmp_path, "box", 32, reframe="sometimes")


def test_sources_keep_the_sample_as_read_and_the_framing_of_its_batch_row(tmp_path):
    sample = build_sample(5, size=96)
    publish(tmp_path, [sample])
    batch = SpoolBatches(tmp_path, "box", 48, reframe="other-sizes", keep_sources=True)[enumerate_spool(tmp_path)]
    (source,) = batch.sources
    assert source.sample == sample
    assert batch.framing[0].tolist() == [source.framing.scale, *source.framing.offset]
    np.testing.assert_allclose(batch.keypoints[0].numpy(), source.framing.to_model(sample.keypoints), atol=1e-4)


def test_a_sample_whose_visible_part_is_a_fragment_is_skipped_as_cut_off(tmp_path):
    from dataclasses import replace

    sample = build_sample(4, size=64)
    fragment = np.zeros_like(sample.noisy)
    fragment[10:14, 10:14] = True  # all that an occluder left visible: a 4 px corner of the wall
    publish(tmp_path, [replace(sample, noisy=fragment)])
    batch = SpoolBatches(tmp_path, "box", 32, reframe="always")[enumerate_spool(tmp_path)]
    assert batch.names == [] and batch.skipped == no_skips(cut_off=1)


def test_a_batch_with_nothing_usable_is_empty_not_an_error(tmp_path):
    names = fill_spool(tmp_path, 1)
    garbage = sample_name()
    (tmp_path / garbage).write_bytes(b"\xc1" * 64)
    os.unlink(tmp_path / names[0])
    batch = SpoolBatches(tmp_path, "box", SIZE)[[names[0], garbage, sample_name(2)]]
    assert batch.names == []
    assert batch.skipped == no_skips(vanished=2, corrupt=1)
    assert batch.noisy is None
    assert SpoolBatches(tmp_path, "box", SIZE)[[]].names == []


# ---- EpochSampler ---------------------------------------------------------------------


def test_an_epoch_is_floor_n_over_batch_batches_of_distinct_spool_names(tmp_path):
    names = fill_spool(tmp_path, 10)
    sampler = EpochSampler(tmp_path, batch_size=3, seed=0)
    batches = consume(sampler)
    assert len(batches) == 3 == len(sampler)
    assert all(len(b) == 3 for b in batches)
    flat = [n for b in batches for n in b]
    assert len(set(flat)) == 9 and set(flat) <= set(names)
    assert sorted(sampler.snapshot().order) == sorted(names)


def test_each_epoch_lists_the_spool_again(tmp_path):
    first = fill_spool(tmp_path, 6)
    sampler = EpochSampler(tmp_path, batch_size=2, seed=0)
    assert sorted(n for b in consume(sampler) for n in b) == sorted(first)
    added = publish(tmp_path, [build_sample(s) for s in (10, 11)])
    epoch1 = [n for b in consume(sampler) for n in b]
    assert sorted(epoch1) == sorted(first + added)
    for name in first[:3]:
        os.unlink(tmp_path / name)
    epoch2 = [n for b in consume(sampler) for n in b]
    assert sorted(sampler.snapshot().order) == sorted(first[3:] + added)
    assert set(epoch2) < set(first[3:] + added) and len(set(epoch2)) == 4  # 5 left, two batches of 2
    assert sampler.where().epoch == 2


def test_epoch_order_is_seeded_and_changes_between_epochs(tmp_path):
    fill_spool(tmp_path, 10)
    a, b, c = (EpochSampler(tmp_path, 2, seed=s) for s in (4, 4, 5))
    a0, b0, c0 = consume(a), consume(b), consume(c)
    assert a0 == b0
    assert a0 != c0
    a1, b1 = consume(a), consume(b)
    assert a1 == b1
    assert a1 != a0


def test_epochs_done_counts_finished_epochs(tmp_path):
    fill_spool(tmp_path, 6)
    sampler = EpochSampler(tmp_path, 2, seed=0)
    assert sampler.epochs_done() == 0
    consume(sampler, batches=2)  # 2 of 3 batches
    assert sampler.epochs_done() == 0
    sampler.advance()  # the trainer takes the third
    assert sampler.epochs_done() == 1
    consume(sampler)
    assert sampler.epochs_done() == 2
    consume(sampler, batches=1)
    assert sampler.epochs_done() == 2


def test_advance_names_the_whole_global_batch_and_end_epoch_finishes_the_epoch(tmp_path):
    names = [sample_name(i) for i in range(10)]
    ranks = [EpochSampler(tmp_path, 2, seed=3, rank=r, world=2, list_spool=lambda _s: names) for r in (0, 1)]
    shares = [next(iter(s)) for s in ranks]
    assert ranks[0].where() == EpochPosition(epoch=0, taken=0, batches=2)
    meant = [s.advance() for s in ranks]
    assert meant[0] == meant[1] == ranks[0].snapshot().order[0:4]  # every rank's share, in listing order
    assert sorted(meant[0]) == sorted(shares[0] + shares[1])
    assert ranks[0].where().taken == 1 and ranks[0].epochs_done() == 0
    ranks[0].end_epoch()  # a stale listing: the rest of the epoch is given up
    assert ranks[0].where() == EpochPosition(epoch=0, taken=2, batches=2) and ranks[0].epochs_done() == 1
    next(iter(ranks[0]))
    assert ranks[0].where() == EpochPosition(epoch=1, taken=0, batches=2)


def test_a_snapshot_is_a_copy_the_sampler_does_not_move(tmp_path):
    fill_spool(tmp_path, 6)
    sampler = EpochSampler(tmp_path, 2, seed=0)
    consume(sampler, batches=1)
    saved = sampler.snapshot()
    assert saved == LoaderState(epoch=0, order=saved.order, position=1, world=1) and len(saved.order) == 6
    consume(sampler)
    assert saved.position == 1 and saved.epoch == 0 and sampler.where().epoch == 1


def test_resume_continues_with_the_batches_after_the_saved_position(tmp_path):
    fill_spool(tmp_path, 12)
    original = EpochSampler(tmp_path, 3, seed=7)
    epoch0 = consume(original)
    epoch1 = consume(original)  # what an uninterrupted run takes next
    saved = LoaderState(epoch=0, order=list(epoch0[0] + epoch0[1] + epoch0[2] + epoch0[3]), position=1)
    publish(tmp_path, [build_sample(20)])  # changes to the spool do not change a saved epoch
    resumed = EpochSampler(tmp_path, 3, seed=7)
    resumed.resume_from(saved)
    assert resumed.epochs_done() == 0
    assert consume(resumed) == epoch0[1:]
    assert resumed.epochs_done() == 1
    os.unlink(tmp_path / enumerate_spool(tmp_path)[-1])  # the spool as the original saw it at epoch 1
    assert consume(resumed) == epoch1
    assert resumed.where().epoch == 1


def test_resume_mid_order_from_a_saved_state_object(tmp_path):
    fill_spool(tmp_path, 8)
    order = enumerate_spool(tmp_path)[::-1]
    sampler = EpochSampler(tmp_path, 2, seed=0)
    sampler.resume_from(LoaderState(epoch=5, order=order, position=3))
    assert consume(sampler) == [order[6:8]]
    assert sampler.where() == EpochPosition(epoch=5, taken=4, batches=4)
    consume(sampler)
    assert sampler.where().epoch == 6


def test_a_spool_smaller_than_a_batch_times_out_naming_the_spool(tmp_path):
    fill_spool(tmp_path, 2)
    sampler = EpochSampler(tmp_path, 4, seed=0, wait=0.02, timeout=0.1)
    with pytest.raises(TimeoutError, match=re.escape(str(tmp_path))):
        next(iter(sampler))


def test_the_sampler_waits_for_a_generator_that_starts_late(tmp_path):
    fill_spool(tmp_path, 1)
    sampler = EpochSampler(tmp_path, 3, seed=0, wait=0.02, timeout=10)
    late = threading.Timer(0.2, lambda: publish(tmp_path, [build_sample(s) for s in (5, 6)]))
    late.start()
    try:
        batches = consume(sampler)
    finally:
        late.join()
    assert len(batches) == 1 and len(set(batches[0])) == 3


def test_make_loader_gives_the_same_batches_with_and_without_workers(tmp_path):
    fill_spool(tmp_path, 7)
    results = []
    for workers in (0, 1):
        loader, sampler = make_loader(tmp_path, "box", SIZE, batch_size=2, seed=3, workers=workers, timeout=1.0)
        epochs = []
        for _ in range(2):
            epochs.append([batch for batch in loader])
        results.append(epochs)
        assert loader.num_workers == workers
        del loader
    (zero, one) = results
    for e0, e1 in zip(zero, one):
        assert len(e0) == len(e1) == 3
        for b0, b1 in zip(e0, e1):
            assert b0.names == b1.names and len(b0.names) == 2
            for key in ("noisy", "clean", "keypoints", "ratios"):
                assert torch.equal(getattr(b0, key), getattr(b1, key)), key
    assert [b.names for b in zero[0]] != [b.names for b in zero[1]]  # a new order each epoch


# ---- FreshnessMeter -------------------------------------------------------------------


def test_freshness_counts_earlier_uses_and_ages_from_names():
    t0 = 1_700_000_000.0
    a, b, c = (sample_name(i, int(t0 * 1e9) + i * 1_000_000_000) for i in range(3))  # published t0, t0+1, t0+2
    fresh = FreshnessMeter()
    age, reuse = fresh.observe([a, b], now=t0 + 10)
    assert age == pytest.approx(9.5) and reuse == 0.0
    age, reuse = fresh.observe([a, b], now=t0 + 20)
    assert age == pytest.approx(19.5) and reuse == 1.0
    age, reuse = fresh.observe([a, c], now=t0 + 20)
    assert age == pytest.approx(19.0) and reuse == 1.0  # a: 2 earlier uses, c: none
    assert fresh.observe([], now=t0) == (0.0, 0.0)
    fresh.forget_except([b, c])  # a was evicted
    assert set(fresh.uses) == {b, c}
    assert fresh.observe([a], now=t0 + 20)[1] == 0.0
    assert fresh.observe([b], now=t0 + 20)[1] == 2.0


# ---- SpoolCensus ----------------------------------------------------------------------


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def names_of(writer: str, seqs, t0: int = 1_700_000_000_000_000_000) -> list[str]:
    return [f"{t0 + s:019d}-{writer}-{s:09d}.cub" for s in seqs]


def test_parse_name_reads_writer_and_sequence_and_refuses_other_forms():
    assert parse_name("1700000000000000000-host-12-ab12cd-000000042.cub") == ("host-12-ab12cd", 42)
    assert parse_name("copied.cub") is None
    assert parse_name("1700000000000000000-host-12-ab12cd-x.cub") is None
    assert published_between({"a": 5, "b": 3}, {"a": 9, "b": 3, "c": 2}) == 4 + 0 + 2  # c started since


def test_census_counts_rate_and_evictions_from_listings_alone():
    clock, spool = Clock(), {"names": names_of("h-1-aa", range(1, 11))}  # 1..10 present
    census = SpoolCensus("unused", refresh_every=30, clock=clock, list_spool=lambda _: spool["names"])
    assert census.count == 10 and census.arrivals_per_s() is None  # one look: no rate yet
    census.read(names_of("h-1-aa", range(1, 11)))  # all ten read before they went
    # 10 s later the writer is at 60; the spool (limit 10) holds 51..60: 50 published,
    # of which 40 (11..50) were evicted before any listing saw them
    clock.now += 10
    spool["names"] = names_of("h-1-aa", range(51, 61))
    assert census.listed(spool["names"]) == {"never_listed": 40, "listed_unread": 0}
    assert census.count == 10 and census.arrivals_per_s() == pytest.approx(5.0)
    # of this listing the loader read 51..54 and 59; 55..58 went unread (vanished, or a stale epoch's rest)
    census.read(names_of("h-1-aa", [51, 52, 53, 54, 59]))
    clock.now += 10
    spool["names"] = names_of("h-1-aa", range(59, 69))  # 61..68 new, 51..58 gone; 59, 60 still there
    assert census.listed(spool["names"]) == {"never_listed": 0, "listed_unread": 4}
    # 59 was read once: its eviction later is not a loss; 60 was never read
    clock.now += 10
    spool["names"] = names_of("h-1-aa", range(61, 71))
    assert census.listed(spool["names"]) == {"never_listed": 0, "listed_unread": 1}
    assert census.evicted_unread == {"never_listed": 40, "listed_unread": 5} and census.evicted_unread_total == 45
    assert census.arrivals_per_s() == pytest.approx(0.2)


def test_census_refreshes_between_epochs_at_most_every_refresh_every_seconds():
    clock, looks = Clock(), []

    def listing(_):
        looks.append(clock.now)
        return names_of("h-1-aa", range(1, int(clock.now) - 99 + 1))  # one sample a second

    census = SpoolCensus("unused", refresh_every=30, clock=clock, list_spool=listing)
    for _ in range(90):  # the dashboard asks once a second
        clock.now += 1
        census.arrivals_per_s()
    assert looks == [100, 130, 160, 190]
    assert census.arrivals_per_s() == pytest.approx(1.0) and census.count == 91
    assert census.listed(listing(None)) == {"never_listed": 0, "listed_unread": 0}  # nothing evicted


def test_census_survives_a_spool_that_goes_away_and_names_of_another_form():
    clock, spool = Clock(), {"names": ["copied.cub", *names_of("h-1-aa", [1, 2])]}

    def listing(_):
        if spool["names"] is None:
            raise FileNotFoundError("gone")
        return spool["names"]

    census = SpoolCensus("unused", clock=clock, list_spool=listing)
    spool["names"] = None
    clock.now += 60
    census.arrivals_per_s()
    assert census.count == 3  # the last figures stay
    with pytest.raises(ValueError, match="refresh_every 0"):
        SpoolCensus("unused", refresh_every=0, list_spool=listing)


def test_census_on_a_real_spool_counts_samples_a_writer_evicted_unlisted(tmp_path):
    fill_spool(tmp_path, 3)
    census = SpoolCensus(tmp_path)
    assert census.count == 3
    publish(tmp_path, [build_sample(s) for s in range(10, 20)], limit=4)  # a new writer: 10 published, 4 kept
    assert census.listed(enumerate_spool(tmp_path))["never_listed"] == 6
    assert census.count == 4


# ---- unpack_masks ---------------------------------------------------------------------


@pytest.mark.parametrize("size", [32, 48, 33])  # 33: 1089 bits, the last byte padded
def test_unpack_masks_inverts_numpy_packbits(size):
    rng = np.random.default_rng(size)
    masks = rng.random((3, size, size)) < 0.4
    packed = np.packbits(masks.reshape(3, -1), axis=1)
    assert packed.shape == (3, (size * size + 7) // 8)
    out = unpack_masks(torch.from_numpy(packed), size)
    assert out.shape == (3, 1, size, size) and out.dtype == torch.float32
    assert torch.equal(out[:, 0], torch.from_numpy(signed(masks)))


@pytest.mark.parametrize("size", [8, 33, 64])
def test_unpack_masks_reads_shared_pack_mask_in_its_bit_order(size):
    # The torch unpacking takes the bit order from shared.sample; a mask packed there comes back whole.
    rng = np.random.default_rng(size + 1)
    masks = rng.random((4, size, size)) < 0.5
    masks[0] = False
    masks[1] = False
    masks[1, 0, 0] = True  # one pixel, the first: a bit order read backwards would put it elsewhere
    packed = np.stack([np.frombuffer(pack_mask(m), np.uint8) for m in masks])
    out = unpack_masks(torch.from_numpy(packed), size)
    assert torch.equal(out[:, 0] > 0, torch.from_numpy(masks))
    assert torch.equal(out[:, 0] > 0, torch.from_numpy(np.stack([unpack_mask(p.tobytes(), size) for p in packed])))


# ---- prepare_batch --------------------------------------------------------------------


def test_prepare_batch_gives_the_samples_own_masks_heatmaps_and_keypoints(tmp_path):
    spool = tmp_path / "spool"
    names = fill_spool(spool, 4)  # seeds 0..3, SIZE px boxes
    seed_of = {name: seed for seed, name in enumerate(names)}
    batch = SpoolBatches(spool, "box", SIZE)[names[::-1]]  # a batch in another order than published
    assert batch.names == names[::-1]
    sigma = 1.0
    x = prepare_batch(batch, CPU, sigma, SIZE)
    n = get_shape("box").num_keypoints
    assert x.x1.shape == x.x2.shape == (4, 1, SIZE, SIZE)
    assert x.x3.shape == (4, n, SIZE, SIZE)
    assert x.x4.shape == (4, n, 2) and x.ratios.shape == (4, 2)
    for b, name in enumerate(batch.names):
        sample = build_sample(seed_of[name])
        assert torch.equal(x.x1[b, 0], torch.from_numpy(signed(sample.noisy)))
        assert torch.equal(x.x2[b, 0], torch.from_numpy(signed(sample.clean)))
        keypoints = torch.from_numpy(sample.keypoints).float()
        assert torch.equal(x.x4[b], keypoints)
        ratios = get_shape("box").ratio_vector(sample.ratios)
        assert torch.allclose(x.ratios[b], torch.from_numpy(ratios).float())
        for k, (kx, ky) in enumerate(sample.keypoints.tolist()):
            want = (min(max(round(ky), 0), SIZE - 1), min(max(round(kx), 0), SIZE - 1))
            assert divmod(int(x.x3[b, k].argmax()), SIZE) == want, (name, k)
    assert torch.equal(x.x3, render_heatmaps(x.x4, SIZE, sigma))
