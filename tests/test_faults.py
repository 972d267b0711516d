"""Faults: a full disk, bad spool paths, corrupt and foreign files, an almost empty spool,
and what a killed trainer leaves behind. The kill -9 soak is benchmarks/soak/soak_faults.py."""
from __future__ import annotations

import errno
import io
import json
import logging
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

import cuboidgen.daemon as daemon
import cuboidtrain.data.sampler as data
import cuboidtrain.train.loop as train_module
from cuboidgen.cli import app as gen_app
from cuboidtrain.models.checkpoint import load_checkpoint
from cuboidtrain.cli import app as train_app
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.train.monitor.dashboard import render, watch
from cuboidtrain.train.run_files import sweep_orphans as sweep_run_folder
from cuboidtrain.train.monitor.status import TrainerStatus, read_status, trainer_died, write_status
from cuboidtrain.train.loop import NoUsableSamples, run
from cuboidtrain.train.stop_and_wait import StopRequest
from shared.files import process_alive, temporary_name
from shared.inspect import inspect_spool
from shared.sample import encode
from shared.spool import SpoolWriter, enumerate_spool
from tests.conftest import ARCH, build_sample, file_size_limit, tiny_config, train_config

ROOT = Path(__file__).resolve().parents[1]
SIZE = 32
runner = CliRunner()


def fill(spool: Path, count: int) -> list[str]:
    with SpoolWriter(spool, limit=0) as writer:
        return [writer.publish(encode(build_sample(seed, size=SIZE))) for seed in range(count)]


def config(spool: Path, out: Path, **changes) -> TrainConfig:
    base = train_config(spool=str(spool), out=str(out), size=SIZE, steps=3, batch_size=2, loader_workers=0,
                       dashboard=False, log_every=1, checkpoint_every=1000)
    return replace(base, **changes).validate()


def stop_at_listing(monkeypatch, count: int) -> tuple[StopRequest, list[float]]:
    """A stop asked for at the trainer's `count`-th listing of the spool; the listings' times."""
    stop, times = StopRequest(), []
    real = data.enumerate_spool

    def listing(spool):
        times.append(time.monotonic())
        if len(times) == count:
            stop.signal = signal.SIGTERM
        return real(spool)

    monkeypatch.setattr(data, "enumerate_spool", listing)
    return stop, times


def shown(status: TrainerStatus) -> str:
    """The dashboard of the status that run() returns."""
    console = Console(width=200, record=True, file=io.StringIO())
    console.print(render(status))
    return console.export_text()


# ---- a full disk ------------------------------------------------------------------------


def workers_shared(workers: int = 1) -> daemon.Shared:
    return daemon.Shared(counters=mp.Array("q", workers * len(daemon.FIELDS), lock=False), stop=mp.RawValue("b", 0),
                         drawn=mp.Value("q", 0), most=None)


def test_a_full_disk_backs_off_says_so_and_resumes_publishing(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(daemon, "BACKOFF", (0.01, 0.02))
    real_pwrite, full_for = os.pwrite, [3]  # the disk is full for three tries

    def pwrite(fd, payload, offset):
        if full_for[0]:
            full_for[0] -= 1
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_pwrite(fd, payload, offset)

    shared, states = workers_shared(), []
    real_pause = daemon.pause
    monkeypatch.setattr(daemon, "pause", lambda s, sh: (states.append(daemon.STATE_NAMES[sh.get(0, "state")]),
                                                        real_pause(s, sh)))
    monkeypatch.setattr(os, "pwrite", pwrite)
    caplog.set_level(logging.INFO, "cuboidgen.daemon")
    with SpoolWriter(tmp_path, limit=10) as writer:
        assert daemon.publish(writer, encode(build_sample(0, size=SIZE)), 0, shared)
    assert states == ["disk full, backing off"] * 3  # said so while it waited
    assert shared.get(0, "state") == daemon.RUNNING
    assert "disk full" in caplog.text and "space again" in caplog.text
    assert os.listdir(tmp_path) == enumerate_spool(tmp_path) and len(os.listdir(tmp_path)) == 1  # no partial file
    assert inspect_spool(tmp_path)["corrupt"] == 0
    shared.set(0, "state", daemon.BACKING_OFF)  # the dashboard's view of a backing-off worker
    view = daemon.snapshot(tiny_config(tmp_path, size=SIZE), shared, [0.0], 1.0)
    assert view.workers[0].state == "disk full, backing off" and "disk full" in view.notes[0]


def remount_read_only(disk: Path, timeout: float = 20.0) -> None:
    """Remount `disk` read-only under a running writer. The kernel refuses (EBUSY) while a file
    there is open for writing, so try again until the writer is between two samples."""
    deadline = time.monotonic() + timeout
    while subprocess.run(["mount", "-o", "remount,ro", str(disk)], capture_output=True).returncode != 0:
        assert time.monotonic() < deadline, f"could not remount {disk} read-only within {timeout} s"
        time.sleep(0.005)


def _mount_tmpfs(where: Path, size: str) -> bool:
    where.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                          capture_output=True).returncode == 0


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small tmpfs needs root")
def test_a_really_full_tmpfs_backs_off_and_publishing_resumes_when_space_returns(tmp_path):
    disk, log = tmp_path / "disk", tmp_path / "generator.log"
    if not _mount_tmpfs(disk, "96k"):
        pytest.skip("cannot mount a tmpfs here")
    proc = None
    try:
        with open(log, "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(disk), "--limit", "0",
                                     "--max-samples", "100000", "--workers", "1", "--size", str(SIZE), "--no-dashboard"],
                                    cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        _wait_for_line(log, "backing off", proc)  # the one worker found the disk full: nothing more is published
        full = len(enumerate_spool(disk))
        assert 0 < full < 100, full  # a 96 KB disk holds a few dozen 4 KB pages
        for name in enumerate_spool(disk)[: full // 2]:  # space returns
            os.unlink(disk / name)
        deadline = time.monotonic() + 30
        while len(enumerate_spool(disk)) < full and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(enumerate_spool(disk)) >= full  # publishing resumed
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        output = log.read_text()
        assert "disk full" in output and "space again" in output, output
        report = inspect_spool(disk)
        assert report["corrupt"] == 0 and report["temporary"] == 0
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        subprocess.run(["umount", str(disk)])


def _wait_for_line(log: Path, words: str, proc: subprocess.Popen, within: float = 60) -> None:
    """Until the generator writing `log` says `words`, while it runs."""
    deadline = time.monotonic() + within
    while words not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None and words in log.read_text(), log.read_text()


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small tmpfs needs root")
def test_a_generator_started_on_a_full_disk_waits_for_space_and_then_publishes(tmp_path):
    # It used to exit on its first write (the spool's SPOOL.json), so a restart needed a hand.
    disk, log = tmp_path / "disk", tmp_path / "generator.log"
    if not _mount_tmpfs(disk, "96k"):
        pytest.skip("cannot mount a tmpfs here")
    proc = None
    try:
        ballast = disk / ".ballast"
        with open(ballast, "wb", buffering=0) as f, pytest.raises(OSError, match="No space left"):
            while True:
                f.write(b"\0" * 4096)
        with open(log, "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(disk), "--limit", "0",
                                     "--max-samples", "5", "--workers", "1", "--size", str(SIZE), "--no-dashboard"],
                                    cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        _wait_for_line(log, "backing off", proc)  # waiting, not gone
        ballast.unlink()
        proc.wait(timeout=60)
        assert proc.returncode == 0 and len(enumerate_spool(disk)) == 5, log.read_text()
        assert "disk full" in log.read_text() and "space again" in log.read_text()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        subprocess.run(["umount", str(disk)])


# ---- bad spool paths: one line, for both daemons ---------------------------------------


def one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), result.output
    return lines[0]


@pytest.mark.parametrize("fault, generator, trainer", [
    ("missing", None, "no such folder"),  # the generator creates a missing spool
    ("file", "not a folder", "not a folder"),
    ("under a file", "cannot create it", "no such folder"),
    ("no permission", "not writable", "not readable"),
])
def test_a_bad_spool_path_is_a_one_line_error_for_both_daemons(tmp_path, monkeypatch, fault, generator, trainer):
    (tmp_path / "file").write_text("not a folder")
    spool = {"missing": tmp_path / "missing", "file": tmp_path / "file", "under a file": tmp_path / "file" / "spool",
             "no permission": tmp_path}[fault]
    if fault == "no permission":
        # Root ignores permissions, so fake them for the daemons' checks (which ask for X_OK
        # too), not for the command line's own readability check of an existing path.
        real_access = os.access
        monkeypatch.setattr(os, "access", lambda path, mode, **k: False if mode & os.X_OK else real_access(path, mode))
    if generator:
        result = runner.invoke(gen_app, ["run", "--spool", str(spool), "--limit", "5", "--max-samples", "1",
                                         "--workers", "1", "--size", str(SIZE), "--no-dashboard"])
        assert generator in one_line_error(result) and str(spool) in result.output
    result = runner.invoke(train_app, ["run", "--spool", str(spool), "--size", str(SIZE), "--steps", "1",
                                       "--out", str(tmp_path / "run"), "--no-dashboard", "--loader-workers", "0"])
    assert trainer in one_line_error(result) and str(spool) in result.output


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting needs root")
def test_a_read_only_spool_is_a_one_line_error_for_the_generator(tmp_path):
    disk = tmp_path / "ro"
    if not _mount_tmpfs(disk, "64k"):
        pytest.skip("cannot mount a tmpfs here")
    try:
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        result = runner.invoke(gen_app, ["run", "--spool", str(disk), "--limit", "5", "--max-samples", "1",
                                         "--workers", "1", "--size", str(SIZE), "--no-dashboard"])
        assert "not writable" in one_line_error(result)
    finally:
        subprocess.run(["umount", str(disk)])


# ---- corrupt and foreign files ------------------------------------------------------------


@pytest.fixture
def polluted(tmp_path) -> Path:
    """Six good samples, three corrupt ones (garbage, empty, truncated), three foreign entries."""
    spool = tmp_path / "spool"
    names = fill(spool, 6)
    stamp = names[-1].split("-")[0]
    (spool / f"{stamp}-x-1-aa-000000001.cub").write_bytes(b"\x00garbage")
    (spool / f"{stamp}-x-1-aa-000000002.cub").write_bytes(b"")
    (spool / f"{stamp}-x-1-aa-000000003.cub").write_bytes((spool / names[0]).read_bytes()[:100])
    (spool / "notes.txt").write_text("someone's notes")
    (spool / "junk").mkdir()
    (spool / f"{stamp}-x-1-aa-000000004.cub").mkdir()  # a folder named like a sample
    return spool


def test_the_trainer_skips_counts_and_reports_corrupt_and_foreign_files(polluted, tmp_path):
    status = run(config(polluted, tmp_path / "run", steps=6))
    assert status.state == "done" and status.step == 6
    assert status.skipped["corrupt"] >= 4  # 4 unreadable names in each of >= 2 epochs of 10 names
    assert status.foreign_files == 2  # notes.txt, junk/ (the sample-named folder counts as corrupt)
    text = " ".join(status.notes)
    assert "corrupt samples skipped" in text and "2 foreign files" in text
    assert "corrupt" in shown(status) and "foreign files" in shown(status)  # on the dashboard


def test_inspect_reports_corrupt_and_foreign_files(polluted):
    result = runner.invoke(gen_app, ["inspect", str(polluted), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["samples"] == 6 and report["corrupt"] == 3 and report["foreign"] == 3


# ---- a trainer far faster than its generator ------------------------------------------


def test_an_empty_spool_waits_saying_so_without_spinning_and_stops_when_asked(tmp_path, monkeypatch, caplog):
    (tmp_path / "spool").mkdir()
    stop, listings = stop_at_listing(monkeypatch, 3)
    caplog.set_level(logging.INFO, "cuboidtrain")
    status = run(config(tmp_path / "spool", tmp_path / "run", steps=None), stop=stop)
    assert status.state == "stopped" and status.step == 0
    assert "holds 0 samples: waiting for at least 2" in caplog.text
    assert len(listings) == 3 and listings[2] - listings[0] >= 0.9  # polled every 0.5 s, not in a busy loop
    assert not (tmp_path / "run" / "last.pt").exists()  # no checkpoint of untrained weights


def test_a_spool_of_three_samples_is_reused_and_says_how_often(tmp_path):
    fill(tmp_path / "spool", 3)
    status = run(config(tmp_path / "spool", tmp_path / "run", steps=8))
    assert status.step == 8 and status.epoch == 7  # one batch of 2 per listing of 3
    assert status.freshness.mean_reuse >= 3  # 16 uses of 3 samples
    assert f"mean reuse {status.freshness.mean_reuse:.1f}" in shown(status)


def test_a_spool_of_only_corrupt_files_waits_rather_than_spins(tmp_path, monkeypatch, caplog):
    spool = tmp_path / "spool"
    spool.mkdir()
    for i in range(3):
        (spool / f"17000000000000000{i:02d}-x-1-aa-00000000{i}.cub").write_bytes(b"not a sample")
    stop, listings = stop_at_listing(monkeypatch, 3)
    caplog.set_level(logging.INFO, "cuboidtrain")
    status = run(config(spool, tmp_path / "run", steps=None), stop=stop)
    assert status.state == "stopped" and status.step == 0
    assert len(listings) == 3 and listings[2] - listings[0] >= 0.9  # a pause between listings: no spinning
    assert status.skipped["corrupt"] == 3 * 2  # one batch of 2 per listing of 3
    assert "no usable sample in the last listing (2 corrupt)" in caplog.text


def test_a_spool_of_unusable_samples_backs_off_says_why_and_writes_no_checkpoint(tmp_path, monkeypatch, caplog):
    # 64 px samples for a 32 px trainer that does not reframe: every listing is unusable.
    spool = tmp_path / "spool"
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(3):
            writer.publish(encode(build_sample(seed, size=64)))
    pauses = []
    monkeypatch.setattr(train_module, "idle_pause", lambda seconds, stop: pauses.append(seconds))
    stop, listings = stop_at_listing(monkeypatch, 9)
    caplog.set_level(logging.INFO, "cuboidtrain")
    status = run(config(spool, tmp_path / "run", steps=None, reframe=False), stop=stop)
    assert status.state == "stopped" and status.step == 0
    assert pauses == [0.5, 1, 2, 4, 8, 16, 30, 30, 30]  # doubling up to 30 s between listings
    reason = "no usable sample in the last listing (2 other size); samples of another size need --reframe"
    assert reason in status.idle and reason in " ".join(status.notes)
    assert "no usable sample" in shown(status)  # on the dashboard
    assert reason in caplog.text and "listing again in 0.5 s" in caplog.text
    assert caplog.text.count(reason) == 1  # the same reason is logged once (again after a minute)
    assert not (tmp_path / "run" / "last.pt").exists()


def test_max_wait_gives_up_on_an_unusable_spool_and_writes_no_checkpoint(tmp_path):
    spool = tmp_path / "spool"
    with SpoolWriter(spool, limit=0) as writer:
        writer.publish(encode(build_sample(0, "twobox", size=SIZE)))
        writer.publish(encode(build_sample(1, "twobox", size=SIZE)))
    started = time.monotonic()
    with pytest.raises(NoUsableSamples, match=r"2 other shape.*no box samples.*gave up after 1 s \(--max-wait 1\)"):
        run(config(spool, tmp_path / "run", steps=None, max_wait=1.0))
    assert time.monotonic() - started >= 1.0
    assert not (tmp_path / "run" / "last.pt").exists()
    assert json.loads((tmp_path / "run" / "status.json").read_text())["state"] == "gave up"


@pytest.mark.parametrize("samples, message", [
    (0, "0 samples after 1 s, need at least one batch (2); gave up (--max-wait 1)"),
    (3, "no usable sample in the last listing (2 other size)"),
])
def test_the_max_wait_option_exits_1_with_a_one_line_error(tmp_path, samples, message):
    spool = tmp_path / "spool"
    spool.mkdir()
    with SpoolWriter(spool, limit=0) as writer:
        for seed in range(samples):
            writer.publish(encode(build_sample(seed, size=64)))
    result = runner.invoke(train_app, ["run", "--spool", str(spool), "--size", str(SIZE), "--batch-size", "2",
                                       "--out", str(tmp_path / "run"), "--no-dashboard", "--loader-workers", "0",
                                       "--arch", ARCH, "--no-reframe", "--max-wait", "1"])
    assert result.exit_code == 1, result.output
    last = result.output.strip().splitlines()[-1]
    assert last.startswith("error: ") and message in last and "Traceback" not in result.output
    assert not (tmp_path / "run" / "last.pt").exists()
    assert runner.invoke(train_app, ["run", "--max-wait", "0"]).exit_code == 2  # a bad value, not a give-up


# ---- what a killed trainer leaves behind ----------------------------------------------


def test_a_restart_sweeps_a_killed_trainers_temporary_files_and_torn_metrics_line(tmp_path):
    fill(tmp_path / "spool", 4)
    out = tmp_path / "run"
    run(config(tmp_path / "spool", out, steps=1))
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (out / temporary_name("last.pt", pid=int(dead.stdout))).write_bytes(b"half a checkpoint")  # killed mid-save
    with open(out / "metrics.jsonl", "a") as f:  # steps 2 and 3 ran after the checkpoint at 1, then a kill
        f.write('{"step": 2, "D_R": 0.5}\n{"step": 3, "D_R": 0.4}\n{"step": 4, "D_R": 0.')  # mid-record
    run(config(tmp_path / "spool", out, steps=2, resume=True))
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")]
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logged] == [1, 2]  # no torn line, and each step once
    assert logged[1]["D_R"] != 0.5  # step 2 is the resumed run's record, not the killed run's


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting needs root")
def test_a_spool_turned_read_only_mid_run_stops_the_generator_with_a_one_line_error(tmp_path):
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "1m"):
        pytest.skip("cannot mount a tmpfs here")
    proc = None
    try:
        proc = subprocess.Popen([sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(disk), "--limit", "20",
                                 "--workers", "1", "--size", str(SIZE), "--no-dashboard"],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})
        deadline = time.monotonic() + 60
        while len(enumerate_spool(disk)) < 20 and time.monotonic() < deadline:
            time.sleep(0.1)
        remount_read_only(disk)
        output = proc.communicate(timeout=60)[0]
        assert proc.returncode == 2, output
        assert f"error: spool {disk}: cannot write to it (Read-only file system)" in output
        assert "Traceback" not in output
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        subprocess.run(["umount", str(disk)])


def test_a_worker_that_cannot_write_stops_every_worker_and_says_why(tmp_path, monkeypatch):
    def read_only(fd, payload, offset):
        raise OSError(errno.EROFS, "Read-only file system")

    shared = workers_shared()
    with SpoolWriter(tmp_path, limit=10) as writer:
        monkeypatch.setattr(os, "pwrite", read_only)
        assert not daemon.publish(writer, encode(build_sample(0, size=SIZE)), 0, shared)
    assert shared.stopping() and shared.get(0, "state") == daemon.FAILED
    assert daemon.failure(shared, 1) == "Read-only file system"
    assert os.listdir(tmp_path) == []


def disk_fills_at(folder: Path, room: int):
    """An os.write that fills the disk under `folder` (ENOSPC) once a file there has taken
    `room` bytes: where the checkpoint writer's every write lands."""
    real_write, written = os.write, {}

    def write(fd, data):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if target.startswith(str(folder)):
            written[target] = written.get(target, 0) + len(data)
            if written[target] > room:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    return write


def open_files_under(folder: Path) -> list[str]:
    """What this process holds open under `folder` (a deleted file shows as 'PATH (deleted)')."""
    held = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder)):
            held.append(target)
    return held


def test_a_checkpoint_that_cannot_be_written_raises_its_oserror_and_leaves_no_file_open_or_behind(tmp_path):
    from cuboidtrain.models.checkpoint import save_checkpoint
    from tests.conftest import tiny_model

    model, cfg = tiny_model("box", SIZE), train_config(size=SIZE)
    save_checkpoint(tmp_path / "last.pt", model, cfg, step=5)
    before = (tmp_path / "last.pt").read_bytes()
    with file_size_limit(64 * 1024), pytest.raises(OSError) as raised:  # a checkpoint is 165 KB
        save_checkpoint(tmp_path / "last.pt", model, cfg, step=10)
    # the disk's own error, not torch's "[enforce fail at inline_container.cc] unexpected pos"
    assert raised.value.errno == errno.EFBIG
    assert os.listdir(tmp_path) == ["last.pt"] and (tmp_path / "last.pt").read_bytes() == before
    assert open_files_under(tmp_path) == []  # the temporary file closed: the disk gets its space back


def test_a_full_disk_mid_checkpoint_fails_the_run_in_one_line_keeping_the_last_checkpoint(tmp_path, monkeypatch):
    fill(tmp_path / "spool", 4)
    out = tmp_path / "run"
    fills = disk_fills_at(out, room=4096)
    real_write = os.write
    # room for one checkpoint: once last.pt exists the next one fails 4 KB in
    monkeypatch.setattr(os, "write", lambda fd, data: (fills if (out / "last.pt").exists() else real_write)(fd, data))
    message = f"out of space writing {out}/last.pt at step 2: kept the step-1 checkpoint (--resume continues it)"
    with pytest.raises(train_module.TrainingFailed) as raised:
        run(config(tmp_path / "spool", out, steps=2, checkpoint_every=1))
    assert str(raised.value) == message
    monkeypatch.setattr(os, "write", real_write)
    assert load_checkpoint(out / "last.pt")["step"] == 1
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")] and open_files_under(out) == []
    status = read_status(out)
    assert status.state == "failed" and status.notes[0] == message


# The trainer, as its own process, on a disk that fills at its second checkpoint: the hang
# (loader workers never stopped) came at interpreter exit, which an in-process run never reaches.
FULL_DISK_TRAINER = """
import resource, sys
import cuboidtrain.train.loop as loop
real_save = loop.save_checkpoint
def save_on_a_full_disk(path, *args, **kwargs):
    if path.exists():  # room for one checkpoint only: writes past 64 KB fail (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
    return real_save(path, *args, **kwargs)
loop.save_checkpoint = save_on_a_full_disk
from cuboidtrain.cli import main
sys.argv = ["cuboidtrain", *sys.argv[1:]]
sys.exit(main())
"""


def test_the_trainer_on_a_full_disk_exits_in_one_line_within_seconds_keeping_its_checkpoint(tmp_path):
    spool, out = tmp_path / "spool", tmp_path / "run"
    fill(spool, 8)
    args = ["run", "--spool", str(spool), "--size", str(SIZE), "--arch", ARCH, "--batch-size", "2",
            "--threads", "1", "--no-dashboard", "--out", str(out), "--steps", "10", "--checkpoint-every", "5",
            "--loader-workers", "2"]
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", FULL_DISK_TRAINER, *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=30)  # the bound: it hung for minutes
    assert time.monotonic() - started < 30
    message = f"cannot write {out}/last.pt at step 10 (File too large): kept the step-5 checkpoint (--resume continues it)"
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == f"error: {message}" and "Traceback" not in proc.stderr
    assert load_checkpoint(out / "last.pt")["step"] == 5  # kept, whole
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")]
    status = read_status(out)
    assert status.state == "failed" and status.notes[0] == message and status.last_checkpoint.step == 5
    assert _processes_naming(str(out)) == []  # the loader workers stopped with it, not left to time out


def _processes_naming(marker: str) -> list[int]:
    """Live processes whose command line holds `marker` (forked loader workers keep their parent's)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if marker.encode() in f.read() and process_alive(int(pid)):
                    found.append(int(pid))
        except OSError:
            continue
    return found


def test_any_failure_mid_run_leaves_the_status_failed_with_the_reason(tmp_path, monkeypatch):
    fill(tmp_path / "spool", 4)
    real_step, calls = train_module.train_step, []

    def breaks_at_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("boom")
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_module, "train_step", breaks_at_the_third)
    with pytest.raises(RuntimeError, match="boom"):
        run(config(tmp_path / "spool", tmp_path / "run", steps=5))
    status = read_status(tmp_path / "run")
    assert status.state == "failed" and status.notes[0] == "RuntimeError: boom" and status.step == 2
    assert not trainer_died(status)  # finished, as `watch` and the healthcheck see it
    assert watch(tmp_path / "run", once=True, console=Console(file=io.StringIO())) == 1


def test_a_zombie_is_dead_to_the_sweep_and_to_watch(tmp_path):
    # A killed daemon's workers can stay zombies (an init that does not reap them): their
    # spares and temporary files must go at the next start, not 60 s later. A zombie trainer
    # died mid-run: watch (and so the compose healthcheck) says so, by the same rule.
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 10
    while open(f"/proc/{child.pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z":  # exited, not reaped
        assert time.monotonic() < deadline
        time.sleep(0.05)
    try:
        assert not process_alive(child.pid) and process_alive(os.getpid())
        (tmp_path / temporary_name("abcdef-spare1.cub", pid=child.pid)).write_bytes(b"x")
        with SpoolWriter(tmp_path, limit=10):  # a writer starting sweeps the spool
            assert os.listdir(tmp_path) == []
        (tmp_path / temporary_name("last.pt", pid=child.pid)).write_bytes(b"x")
        assert sweep_run_folder(tmp_path) == 1 and os.listdir(tmp_path) == []
        write_status(tmp_path / "run", TrainerStatus(state="training", pid=child.pid))
        assert trainer_died(read_status(tmp_path / "run"))
        assert watch(tmp_path / "run", once=True, console=Console(file=io.StringIO())) == 1
    finally:
        child.wait()
