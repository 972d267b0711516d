"""The generator daemon: max-samples, the cap, clean SIGTERM/SIGINT shutdown, limit 0 and metadata."""
import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import cuboidgen.daemon as daemon
from cuboidgen.daemon import run
from shared.inspect import inspect_spool
from shared.sample import VERSION
from shared.spool import META_NAME, enumerate_spool
from tests.conftest import groups_end, tiny_config

ROOT = Path(__file__).resolve().parents[1]


def test_max_samples_publishes_exactly_that_many(tmp_path):
    config = tiny_config(tmp_path, limit=0, max_samples=25, workers=2)
    assert run(config) == 25
    report = inspect_spool(tmp_path)
    assert report["samples"] == 25 and report["corrupt"] == 0 and report["size"] == 48


def test_limit_rotates_the_spool(tmp_path):
    config = tiny_config(tmp_path, limit=10, max_samples=40, workers=2, evict_every=4)
    run(config)
    # The contract's bound is the upper one. Each writer evicts by what it last listed, so on a
    # loaded machine two may each take one the other already replaced: at most one a writer below.
    assert 10 - 2 <= len(enumerate_spool(tmp_path)) <= 10 + 2 * 4


def test_same_seed_same_spool_contents(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for spool in (a, b):
        run(tiny_config(spool, limit=0, max_samples=6, workers=1, seed=9))
    read = lambda s: sorted((s / n).read_bytes() for n in enumerate_spool(s))  # noqa: E731
    assert read(a) == read(b)


def test_a_seed_means_the_same_samples_whatever_the_number_of_workers(tmp_path):
    # Each worker used to number its own samples' seeds, so which worker took how many of the
    # --max-samples tickets changed the set; the run now numbers them across workers.
    spools = {workers: tmp_path / f"w{workers}" for workers in (1, 2, 3)}
    for workers, spool in spools.items():
        run(tiny_config(spool, limit=0, max_samples=12, workers=workers, seed=9))
    read = lambda s: sorted((s / n).read_bytes() for n in enumerate_spool(s))  # noqa: E731
    one = read(spools[1])
    assert len(one) == len(set(one)) == 12
    assert read(spools[2]) == one and read(spools[3]) == one


def test_limit_zero_without_max_samples_leaves_the_spool_as_it_is(tmp_path):
    run(tiny_config(tmp_path, limit=0, max_samples=3))
    before = sorted(os.listdir(tmp_path))
    assert run(tiny_config(tmp_path, limit=0, max_samples=None)) == 0
    assert sorted(os.listdir(tmp_path)) == before


def test_metadata_records_the_config(tmp_path):
    run(tiny_config(tmp_path, max_samples=2, shape="twobox"))
    meta = json.loads((tmp_path / META_NAME).read_text())
    assert meta["version"] == VERSION and meta["generator"]["shape"] == "twobox"
    assert meta["generator"]["scene"]["name"] == "paper"


def start_daemon(spool: Path) -> subprocess.Popen:
    """The daemon in a session of its own: its workers share its process group, whose id is its pid."""
    return subprocess.Popen(
        [sys.executable, "-m", "cuboidgen.cli", "run", "--spool", str(spool), "--limit", "30", "--workers", "2",
         "--size", "32", "--no-dashboard"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(ROOT)},
        start_new_session=True,
    )


def wait_for_samples(spool: Path, count: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not spool.is_dir() or len(enumerate_spool(spool)) < count:
        assert time.monotonic() < deadline, "the daemon published nothing"
        time.sleep(0.1)


def test_sigterm_and_sigint_stop_cleanly_without_torn_files(tmp_path):
    for sig in (signal.SIGTERM, signal.SIGINT):
        spool = tmp_path / sig.name
        daemon = start_daemon(spool)
        wait_for_samples(spool, 30)
        daemon.send_signal(sig)
        output = daemon.communicate(timeout=30)[0].decode()
        assert daemon.returncode == 0, output
        assert "stopped:" in output
        report = inspect_spool(spool)
        # Writers evict without coordinating, so a spool at its limit (30) can dip a little
        # below it: the contract bounds it from above (30 + 2 workers x 64), not from below.
        assert report["corrupt"] == 0 and report["temporary"] == 0
        assert 0 < report["samples"] <= 30 + 2 * 64


def test_kill_9_and_restart_cycles_leave_nothing_corrupt_and_no_orphans(tmp_path):
    # Kill early (workers still starting) and late (workers publishing): both must leave
    # no torn sample and no worker running on without its daemon.
    killed = set()  # the killed daemons' process groups: their workers' too
    for delay in (0.3, 1.0, None, 0.6, None):
        daemon = start_daemon(tmp_path)
        killed.add(daemon.pid)
        if delay is None:
            wait_for_samples(tmp_path, 10)
        else:
            time.sleep(delay)
        daemon.kill()  # SIGKILL to the main process: its workers must notice and exit on their own
        daemon.wait()
    assert groups_end(killed, within=20.0), "workers outlived their killed daemon"
    daemon = start_daemon(tmp_path)  # sweeps orphaned temporary files at start
    wait_for_samples(tmp_path, 30)
    daemon.send_signal(signal.SIGTERM)
    daemon.communicate(timeout=30)
    report = inspect_spool(tmp_path)
    assert report["corrupt"] == 0 and report["temporary"] == 0


class FinishingWorker:
    """A worker process stand-in that finishes its sample in hand when joined."""

    def __init__(self, index: int, shared):
        self.index, self.shared, self.name = index, shared, f"fake-{index}"

    def is_alive(self) -> bool:
        return self.shared.get(self.index, "state") == daemon.RUNNING

    def join(self, timeout=None) -> None:
        self.shared.set(self.index, "published", self.shared.get(self.index, "published") + 1)
        self.shared.set(self.index, "state", daemon.DONE)

    def kill(self) -> None:
        raise AssertionError("a finishing worker needs no kill")


def test_after_a_stop_the_last_frame_shows_the_workers_stopped_with_their_final_counts(tmp_path, monkeypatch):
    frames = []

    class Recorder:
        def __init__(self, live):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

        def due(self, final=False):
            return True

        def update(self, snapshot, final=False):
            frames.append((snapshot, final))

    monkeypatch.setattr(daemon, "Dashboard", Recorder)
    ctx = mp.get_context("spawn")
    shared = daemon.Shared(counters=ctx.Array("q", 2 * len(daemon.FIELDS), lock=False), stop=ctx.RawValue("b", 0),
                           drawn=ctx.Value("q", 0), most=None)
    for i, published in enumerate((7, 9)):
        shared.set(i, "published", published)
    stop = threading.Event()
    stop.set()  # Ctrl-C
    config = tiny_config(tmp_path / "spool")
    (tmp_path / "spool").mkdir()
    daemon.watch(config, shared, [FinishingWorker(i, shared) for i in range(2)], stop)
    (stopping, final_a), (last, final_b) = frames  # one frame while stopping, then the outcome
    assert final_a and final_b
    assert [w.state for w in stopping.workers] == ["stopping", "stopping"] and "stopping" in " ".join(stopping.notes)
    assert [w.state for w in last.workers] == ["done", "done"] and not last.notes
    assert [w.published for w in last.workers] == [8, 10] and last.published == 18  # counted after the join
    assert shared.stopping()


# ---- --max-rate: the throttle ---------------------------------------------------------


class FakeClock:
    def __init__(self):
        self.now = 50.0

    def __call__(self) -> float:
        return self.now


def test_token_bucket_spaces_takes_at_the_rate_and_refills_at_most_a_burst():
    clock = FakeClock()
    bucket = daemon.TokenBucket(rate=4.0, burst=1.0, clock=clock)
    assert bucket.take() == 0.0  # the first token is there
    assert bucket.take() == 0.25  # the next one a quarter second on
    clock.now += 0.25  # the worker waited it out
    assert bucket.take() == 0.25
    clock.now += 0.25
    clock.now += 10.0  # a slow draw: the bucket refills, but to one token only
    assert bucket.take() == 0.0
    assert bucket.take() == 0.25
    clock.now += 0.25
    # over many takes, the waits add up to the rate exactly
    waited = 0.0
    for _ in range(400):
        wait = bucket.take()
        clock.now += wait
        waited += wait
    assert waited == pytest.approx(400 / 4.0)


def test_token_bucket_refuses_a_rate_that_is_not_positive():
    with pytest.raises(ValueError, match="rate 0"):
        daemon.TokenBucket(rate=0)


@pytest.mark.parametrize("rate", [0, -1.0, float("nan")])
def test_max_rate_must_be_positive(tmp_path, rate):
    with pytest.raises(ValueError, match=r"--max-rate .*: expected a finite number > 0 \(samples a second\)"):
        tiny_config(tmp_path, max_rate=rate).validate()


def test_max_rate_spaces_the_publishes_of_a_running_daemon(tmp_path):
    # 10 a second, one worker: 6 samples take at least 5 tenths from the first draw to the
    # last publish (a lower bound only; a busy machine may be slower, never faster)
    run(tiny_config(tmp_path, limit=0, max_samples=6, workers=1, max_rate=10.0))
    times = [int(n.split("-", 1)[0]) / 1e9 for n in enumerate_spool(tmp_path)]
    assert len(times) == 6 and times[-1] - times[0] >= 0.4


def test_max_rate_option_and_its_environment_variable_reach_the_config(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from cuboidgen.cli import app

    seen = []
    monkeypatch.setattr(daemon, "run", lambda config: seen.append(config.max_rate))
    spool = ["--spool", str(tmp_path / "s"), "--no-dashboard"]
    assert CliRunner().invoke(app, ["run", *spool, "--max-rate", "2.5"]).exit_code == 0
    assert CliRunner().invoke(app, ["run", *spool], env={"CUBOIDGEN_MAX_RATE": "7"}).exit_code == 0
    assert seen == [2.5, 7.0]
    result = CliRunner().invoke(app, ["run", *spool, "--max-rate", "0"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "--max-rate 0" in lines[0], result.output


def test_the_watch_loop_wakes_as_a_worker_ends_not_after_its_interval():
    """A run of --max-samples returns as its last worker exits: the loop's wait between frames ends
    with the worker (here a minute's interval, over long before), and a stop asked for waits for nothing."""
    ctx = mp.get_context("spawn")
    worker = ctx.Process(target=time.sleep, args=(0.0,))
    worker.start()
    started = time.monotonic()
    daemon._until_a_worker_ends([worker], threading.Event(), seconds=60.0)
    waited = time.monotonic() - started
    worker.join(30.0)  # its sentinel is ready as it exits, a moment before it is reaped
    assert waited < 30.0 and worker.exitcode == 0
    stop = threading.Event()
    stop.set()
    started = time.monotonic()
    daemon._until_a_worker_ends([FinishingWorker(0, None)], stop, seconds=60.0)  # no sentinel read, no wait
    assert time.monotonic() - started < 1.0
