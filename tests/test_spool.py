"""The spool: atomic publish, the cap, age order, several writers, kill -9, and readers under eviction."""
import errno
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from shared.files import host_tag, sweep_orphans, temporary_name
from shared.sample import decode, encode
from shared.spool import (
    LOCAL_FILESYSTEMS, ORPHAN_AGE, SpoolError, SpoolFull, SpoolWriter, check_spool, enumerate_spool, filesystem_type,
    read_sample_bytes,
)
from tests.conftest import build_sample, fill_spool

ROOT = Path(__file__).resolve().parents[1]


def start_writer(spool, limit, count, evict_every=8, size=32) -> subprocess.Popen:
    process = subprocess.Popen(
        [sys.executable, "-m", "tests.spool_writer", str(spool), str(limit), str(count), str(evict_every), str(size)],
        cwd=ROOT, stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert process.stdout.readline().strip() == b"ready"
    return process


def test_publish_then_read_back_in_age_order(tmp_path, library):
    names = fill_spool(tmp_path, 5, library=library)
    assert enumerate_spool(tmp_path) == names == sorted(names)
    for seed, name in enumerate(names):
        assert decode(read_sample_bytes(tmp_path, name)) == build_sample(seed, library=library)
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # no temporary files left


def test_limit_evicts_the_oldest_first(tmp_path, library):
    names = fill_spool(tmp_path, 30, limit=10, library=library)
    assert enumerate_spool(tmp_path) == names[-10:]


def test_limit_zero_retains_everything(tmp_path, library):
    fill_spool(tmp_path, 12, library=library)
    fill_spool(tmp_path, 5, limit=0, library=library)
    assert len(enumerate_spool(tmp_path)) == 17


def test_a_new_writer_evicts_down_to_its_limit_at_start(tmp_path, library):
    names = fill_spool(tmp_path, 12, library=library)
    with SpoolWriter(tmp_path, limit=4):
        assert enumerate_spool(tmp_path) == names[-4:]


def test_names_never_collide_between_writers(tmp_path):
    with SpoolWriter(tmp_path, 0) as a, SpoolWriter(tmp_path, 0) as b:
        names = {a.publish(b"x") for _ in range(200)} | {b.publish(b"y") for _ in range(200)}
    assert len(names) == 400 == len(enumerate_spool(tmp_path))


def test_concurrent_writers_stay_within_the_stated_bound(tmp_path):
    limit, evict_every, writers, count = 40, 8, 3, 300
    bound = limit + writers * evict_every  # shared/spool.py's promise
    processes = [start_writer(tmp_path, limit, count, evict_every) for _ in range(writers)]
    peak = 0
    while any(p.poll() is None for p in processes):
        peak = max(peak, len(enumerate_spool(tmp_path)))
    assert all(p.returncode == 0 for p in processes)
    final = len(enumerate_spool(tmp_path))
    assert peak <= bound and limit <= final <= bound
    assert peak > limit // 2  # the monitor really watched a full spool


def test_kill_9_while_writing_never_leaves_a_torn_sample(tmp_path):
    rng = random.Random(7)
    for _ in range(8):
        writer = start_writer(tmp_path, limit=30, count=0, evict_every=4, size=256)
        time.sleep(rng.uniform(0.05, 0.4))
        writer.send_signal(signal.SIGKILL)
        writer.wait()
        for name in enumerate_spool(tmp_path):
            data = read_sample_bytes(tmp_path, name)
            assert data is None or decode(data).size == 256  # ValueError here would be a torn sample
    with SpoolWriter(tmp_path, limit=30):
        pass  # a new writer sweeps what the killed ones left
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".tmp-")]
    assert len(enumerate_spool(tmp_path)) == 30


def test_reader_survives_eviction_during_enumeration(tmp_path):
    writer = start_writer(tmp_path, limit=10, count=0, evict_every=2)
    vanished = read = 0
    deadline = time.monotonic() + 30  # until both were seen: waited on, not slept for
    try:
        while time.monotonic() < deadline and not (read and vanished):
            for name in enumerate_spool(tmp_path):
                data = read_sample_bytes(tmp_path, name)
                if data is None:
                    vanished += 1
                else:
                    decode(data)
                    read += 1
    finally:
        writer.kill()
        writer.wait()
    assert read > 0 and vanished > 0


def test_sweep_removes_orphans_of_dead_writers_only(tmp_path):
    sample = "0000000000000000001-somehost-12-abc-000000001.cub"
    dead = tmp_path / temporary_name(sample, pid=999999)
    live = tmp_path / temporary_name(sample)
    stale = tmp_path / temporary_name(sample, host="otherhost", pid=12)  # another host's: only age tells
    fresh = tmp_path / temporary_name("abc-spare0.cub", host="otherhost", pid=12)
    older_version = tmp_path / f".tmp-1-{host_tag()}-999999-abc-000000001.cub"  # a time in the first field
    for path in (dead, live, stale, fresh, older_version):
        path.write_bytes(b"partial")
    os.utime(stale, (time.time() - ORPHAN_AGE - 1, time.time() - ORPHAN_AGE - 1))
    assert sweep_orphans(tmp_path, ORPHAN_AGE) == 3
    assert sorted(os.listdir(tmp_path)) == sorted([live.name, fresh.name])


def test_a_writer_starting_sweeps_a_dead_writers_temporaries_and_spares(tmp_path):
    for name in ("0000000000000000001-x-1-abc-000000001.cub", "abc-spare1.cub"):
        (tmp_path / temporary_name(name, pid=999999)).write_bytes(b"partial")
    with SpoolWriter(tmp_path, limit=10) as writer:
        name = writer.publish(b"sample")
    assert os.listdir(tmp_path) == [name]


@pytest.mark.parametrize("recycle", [False, True])
def test_full_disk_publishes_nothing_and_says_so(tmp_path, monkeypatch, recycle):
    def full_disk(fd, data, offset):
        raise OSError(errno.ENOSPC, "No space left on device")

    with SpoolWriter(tmp_path, limit=5, recycle=recycle) as writer:
        monkeypatch.setattr(os, "pwrite", full_disk)
        with pytest.raises(SpoolFull, match="no space left"):
            writer.publish(b"data")
        monkeypatch.undo()
        assert os.listdir(tmp_path) == []
        names = [writer.publish(encode(build_sample(seed))) for seed in range(7)]  # at the limit: evicting
        monkeypatch.setattr(os, "pwrite", full_disk)  # now with an evicted file in hand to rewrite
        for _ in range(2):  # and again without one
            with pytest.raises(SpoolFull, match="no space left"):
                writer.publish(b"data")
            assert sorted(os.listdir(tmp_path)) == names[-5:]  # nothing published or evicted, nothing partial left
        monkeypatch.undo()
        writer.publish(encode(build_sample(0)))  # space is back: publishing resumes
    assert len(enumerate_spool(tmp_path)) == 5


def recycles_here(path) -> bool:
    return filesystem_type(path) in LOCAL_FILESYSTEMS


def test_recycling_rewrites_evicted_files_but_never_one_a_reader_holds(tmp_path, library):
    data = [encode(build_sample(seed, library=library)) for seed in range(12)]
    inodes = []
    with SpoolWriter(tmp_path, limit=3, recycle=True) as writer:
        def publish(payload):
            name = writer.publish(payload)
            inodes.append(os.stat(tmp_path / name).st_ino)
            return name

        names = [publish(d) for d in data[:3]]
        with open(tmp_path / names[0], "rb") as held:  # a reader opened the oldest sample
            names += [publish(d) for d in data[3:]]  # evicts it (and the next ones)
            assert held.read() == data[0]  # its bytes were left alone
    assert enumerate_spool(tmp_path) == names[-3:]
    assert [read_sample_bytes(tmp_path, n) for n in names[-3:]] == data[-3:]
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # the spare goes with the writer
    if recycles_here(tmp_path):
        # Sample 1's file, evicted by the fifth publish, was rewritten as the sixth sample;
        # sample 0's, held by a reader, was not reused.
        assert inodes[5] == inodes[1] and inodes[0] not in inodes[3:]


def test_a_file_with_another_name_is_not_rewritten(tmp_path, library):
    # Two writers can evict the same sample, each linking it as its spare; a copy made
    # with hard links (cp -l) shares it too: then it must not be rewritten.
    data = [encode(build_sample(seed, library=library)) for seed in range(4)]
    with SpoolWriter(tmp_path, limit=2, recycle=True) as writer:
        names = [writer.publish(d) for d in data[:2]]
        os.link(tmp_path / names[0], tmp_path / ".tmp-0-otherwriter-spare.cub")
        names += [writer.publish(d) for d in data[2:]]  # the first evicts (and would reuse) sample 0
    assert [read_sample_bytes(tmp_path, n) for n in enumerate_spool(tmp_path)] == data[2:]
    assert (tmp_path / ".tmp-0-otherwriter-spare.cub").read_bytes() == data[0]


def test_readers_holding_samples_never_see_them_rewritten(tmp_path):
    """Recycling under load: a reader that opened a sample reads exactly the bytes published."""
    from cuboidgen.config import PAPER
    from cuboidgen.occluders import OccluderLibrary
    from cuboidgen.synth import make_sample

    library = OccluderLibrary.builtin(variants_per_kind=1)  # what tests/spool_writer.py publishes
    published = {encode(make_sample("box", PAPER, 32, seed, library)) for seed in range(8)}
    writer = start_writer(tmp_path, limit=10, count=0, evict_every=4)
    recycling = recycles_here(tmp_path)
    read = reused = 0
    names_of = {}  # inode -> the sample name it was last seen under
    # Until files came back under new names a few times while read (1.5 s where nothing recycles)
    deadline = time.monotonic() + (30 if recycling else 1.5)
    try:
        while time.monotonic() < deadline and not (recycling and reused >= 5):
            for name in enumerate_spool(tmp_path):
                try:
                    f = open(tmp_path / name, "rb")
                except FileNotFoundError:
                    continue
                with f:
                    inode = os.fstat(f.fileno()).st_ino
                    reused += names_of.setdefault(inode, name) != name
                    names_of[inode] = name
                    time.sleep(0.0005)  # hold it open while the writer evicts and recycles
                    assert f.read() in published
                read += 1
    finally:
        writer.kill()
        writer.wait()
    assert read > 0
    if recycling:
        assert reused > 0  # the writer really was recycling: files came back under new names


def test_filesystem_type_names_the_mount():
    assert filesystem_type(Path("/proc")) == "proc"
    assert filesystem_type(Path("/no/such/path")) is None


def test_bad_spool_paths_are_one_line_errors(tmp_path, monkeypatch):
    with pytest.raises(SpoolError, match="no such folder"):
        check_spool(tmp_path / "missing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(SpoolError, match="not a folder"):
        check_spool(tmp_path / "file")
    monkeypatch.setattr(os, "access", lambda *a: False)  # root ignores permissions, so fake them
    with pytest.raises(SpoolError, match="not writable"):
        check_spool(tmp_path, writable=True)


def test_writer_creates_a_missing_spool(tmp_path):
    with SpoolWriter(tmp_path / "a" / "b", limit=3) as writer:
        writer.publish(b"x")
    assert len(enumerate_spool(tmp_path / "a" / "b")) == 1


def test_a_spool_another_generator_made_meanwhile_is_used_not_refused(tmp_path, monkeypatch):
    spool = tmp_path / "spool"
    spool.mkdir()  # made by another generator between this one's look and its own mkdir
    real, looks = Path.exists, []

    def exists(self, *args, **kwargs):
        if self == spool and not looks:  # the first look: not there yet
            looks.append(self)
            return False
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "exists", exists)
    assert check_spool(spool, writable=True, create=True) == spool and looks


def test_a_file_in_a_new_spools_place_is_not_a_folder(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(SpoolError, match="not a folder"):
        check_spool(tmp_path / "file", create=True)


def test_negative_limit_is_refused(tmp_path):
    with pytest.raises(ValueError, match="limit -1"):
        SpoolWriter(tmp_path, -1)


def test_read_survives_short_reads(tmp_path, monkeypatch, library):
    data = encode(build_sample(0, library=library))
    with SpoolWriter(tmp_path, limit=0) as writer:
        name = writer.publish(data)
    real_read = os.read
    monkeypatch.setattr(os, "read", lambda fd, n: real_read(fd, min(n, 1000)))
    assert read_sample_bytes(tmp_path, name) == data
    assert read_sample_bytes(tmp_path, "gone.cub") is None


@pytest.mark.parametrize("size", [48, 14])  # 14 x 14 bits do not fill whole bytes
def test_collated_masks_are_the_decoded_ones(tmp_path, size, library):
    from shared.sample import collate, decode_packed

    with SpoolWriter(tmp_path, limit=0) as writer:
        for seed in range(5):
            writer.publish(encode(build_sample(seed, size=size, library=library)))
    data = [read_sample_bytes(tmp_path, n) for n in enumerate_spool(tmp_path)]
    batch = collate([decode_packed(d) for d in data], unpack=True)
    for key in ("noisy", "clean"):
        expected = np.stack([getattr(decode(d), key) for d in data]).astype(np.uint8)
        assert batch[key].dtype == np.uint8 and batch[key].shape == (5, size, size)
        assert (batch[key] == expected).all()
