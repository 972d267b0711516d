"""The generator daemon: N worker processes publish samples into the spool.

Every worker is a spool writer of its own (it publishes and evicts), so the
daemon needs no coordinator: the main process only starts workers, watches
their counters and the spool, shows the dashboard and stops everyone on
SIGINT/SIGTERM. Workers finish the sample in hand before they exit; since
publishing is a rename, even a SIGKILL never leaves a torn sample.
"""
from __future__ import annotations

import errno
import logging
import multiprocessing as mp
import os
import secrets
import signal
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_for_any
from pathlib import Path

from cuboidgen.config import GenConfig
from cuboidgen.dashboard import Dashboard, GenSnapshot, WorkerView
from shared.files import write_json
from shared.sample import encode
from shared.spool import META_NAME, SpoolError, SpoolFull, SpoolWriter, check_spool, enumerate_spool, name_time

log = logging.getLogger(__name__)

# Per-worker counters in shared memory, one row of these fields per worker.
FIELDS = ("published", "evicted", "errors", "state", "bytes", "errno")
RUNNING, BACKING_OFF, DONE, FAILED = 0, 1, 2, 3
STATE_NAMES = {RUNNING: "running", BACKING_OFF: "disk full, backing off", DONE: "done", FAILED: "failed: cannot write"}
BACKOFF = (0.5, 10.0)  # s: first and longest wait while the disk is full
JOIN_TIMEOUT = 15.0  # s a worker gets to finish its sample before it is killed
WATCH_SECONDS = 0.5  # s between the watch loop's looks at the workers, unless one ends sooner


@dataclass
class Shared:
    """What the main process and its workers share (never the trainer)."""

    counters: object  # mp.Array of int64, workers x FIELDS
    stop: object  # mp.RawValue flag: lock-free, so a killed process can never leave it locked
    drawn: object  # mp.Value: the run's samples handed out so far, across workers (each one's index)
    most: int | None  # --max-samples: no index from it on is handed out

    def stopping(self) -> bool:
        return bool(self.stop.value)

    def request_stop(self) -> None:
        self.stop.value = 1

    def set(self, worker: int, name: str, value: int) -> None:
        self.counters[worker * len(FIELDS) + FIELDS.index(name)] = value

    def get(self, worker: int, name: str) -> int:
        return self.counters[worker * len(FIELDS) + FIELDS.index(name)]

    def next_index(self) -> int | None:
        """The run's next sample index (its seed's), None once --max-samples are handed out. One
        count for all workers, so the run's samples are the same whatever the number of workers."""
        with self.drawn.get_lock():
            index = self.drawn.value
            if self.most is not None and index >= self.most:
                return None
            self.drawn.value = index + 1
            return index


def run(config: GenConfig) -> int:
    """Generate until stopped (or --max-samples); returns the number of samples published."""
    config.validate()
    if config.limit == 0 and config.max_samples is None:
        log.warning("--limit 0 retains the spool as it is: nothing to generate "
                    "(add --max-samples N to append N samples without eviction)")
        return 0
    check_spool(config.spool, writable=True, create=True)
    write_metadata(config)
    seed = config.seed if config.seed is not None else secrets.randbits(63)
    ctx = mp.get_context("spawn")
    shared = Shared(
        counters=ctx.Array("q", config.workers * len(FIELDS), lock=False),
        stop=ctx.RawValue("b", 0),
        drawn=ctx.Value("q", 0),
        most=config.max_samples or None,
    )
    workers = [ctx.Process(target=work, args=(i, config, seed, shared, os.getpid()), daemon=True,
                           name=f"cuboidgen-{i}")
               for i in range(config.workers)]
    stop_asked = threading.Event()
    previous = _install_stop_handlers(stop_asked)
    try:
        for w in workers:
            w.start()
        log.info("generating into %s with %d workers, run seed %d", config.spool, config.workers, seed)
        watch(config, shared, workers, stop_asked)
    finally:
        shared.request_stop()
        _join(workers)
        _restore_handlers(previous)
    published = sum(shared.get(i, "published") for i in range(config.workers))
    log.info("stopped: %d samples published", published)
    reason = failure(shared, config.workers)
    if reason:
        raise SpoolError(f"spool {config.spool}: cannot write to it ({reason})")
    return published


class TokenBucket:
    """At most `rate` takes a second on average, in bursts of at most `burst`: --max-rate's
    throttle. `take` reserves a token and says how long to wait for it, so a worker sleeps
    before drawing (no CPU spent on samples it may not publish yet). `clock` is injectable:
    the tests check the arithmetic without sleeping."""

    def __init__(self, rate: float, burst: float = 1.0, clock=time.monotonic):
        if not rate > 0:
            raise ValueError(f"rate {rate}: expected a positive number of samples a second")
        self.rate, self.burst, self.clock = rate, burst, clock
        self.tokens, self.last = burst, clock()

    def take(self) -> float:
        """Seconds to wait before the next sample (0 while a token is there)."""
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        self.tokens -= 1  # below zero: a reservation, repaid by waiting
        return 0.0 if self.tokens >= 0 else -self.tokens / self.rate


def work(index: int, config: GenConfig, run_seed: int, shared: Shared, parent: int) -> None:
    """One worker: draw, encode, publish, repeat. Runs in its own process.

    `parent` is the main process's pid, passed in rather than read here: a main
    process killed while this one starts up would otherwise go unnoticed.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the main process decides when to stop
    signal.signal(signal.SIGTERM, lambda *_: shared.request_stop())
    import cv2

    cv2.setNumThreads(1)  # one process per core: OpenCV's own threads only contend
    from cuboidgen.occluders import OccluderLibrary
    from cuboidgen.synth import make_sample, sample_seed

    library = OccluderLibrary.load(config.occluders)
    if os.getppid() != parent:
        return  # the daemon died while we started: touch nothing (not even an eviction)
    # Each worker takes an equal share of --max-rate: no lock between processes on the hot path.
    bucket = TokenBucket(config.max_rate / config.workers) if config.max_rate else None
    with SpoolWriter(config.spool, config.limit, config.evict_every, config.fsync) as writer:
        # A SIGKILLed main process cannot tell us to stop: being re-parented is the sign.
        while not shared.stopping() and os.getppid() == parent and (number := shared.next_index()) is not None:
            if bucket is not None:
                pause(bucket.take(), shared)
                if shared.stopping():
                    break
            seed = sample_seed(run_seed, 0, number)  # stream 0: numbered across workers
            try:
                data = encode(make_sample(config.shape, config.scene, config.size, seed, library))
            except Exception:  # a bad draw must not stop the daemon; it is counted and logged
                log.exception("worker %d: sample with seed %d failed", index, seed)
                shared.set(index, "errors", shared.get(index, "errors") + 1)
                continue
            if not publish(writer, data, index, shared):
                break
            shared.set(index, "published", writer.counts.published)
            shared.set(index, "evicted", writer.counts.evicted)
            shared.set(index, "bytes", writer.counts.published_bytes)
    if shared.get(index, "state") != FAILED:
        shared.set(index, "state", DONE)


def publish(writer: SpoolWriter, data: bytes, index: int, shared: Shared) -> bool:
    """Publish, waiting out a full disk with growing pauses; False if stopped meanwhile."""
    wait = BACKOFF[0]
    while not shared.stopping():
        try:
            writer.publish(data)
            if shared.get(index, "state") == BACKING_OFF:
                log.warning("worker %d: space again under %s, publishing", index, writer.spool)
            shared.set(index, "state", RUNNING)
            return True
        except SpoolFull:
            if shared.get(index, "state") != BACKING_OFF:
                log.warning("worker %d: disk full under %s, backing off", index, writer.spool)
            shared.set(index, "state", BACKING_OFF)
            pause(wait, shared)
            wait = min(wait * 2, BACKOFF[1])
        except OSError as exc:  # read-only, permissions gone, folder removed: waiting will not help
            log.error("worker %d: cannot write to %s (%s); stopping", index, writer.spool, exc.strerror)
            shared.set(index, "errno", exc.errno or errno.EIO)
            shared.set(index, "state", FAILED)
            shared.request_stop()  # every worker: the spool is unusable for all of them
            return False
    return False


def failure(shared: Shared, workers: int) -> str | None:
    """Why a worker could not write to the spool (its error's text), or None."""
    for i in range(workers):
        if shared.get(i, "state") == FAILED:
            return os.strerror(shared.get(i, "errno"))
    return None


def pause(seconds: float, shared: Shared) -> None:
    """Sleep, waking early when a stop is asked for."""
    deadline = time.monotonic() + seconds
    while not shared.stopping() and time.monotonic() < deadline:
        time.sleep(min(0.1, seconds))


def watch(config: GenConfig, shared: Shared, workers: list, stop_asked: threading.Event) -> None:
    """Refresh the dashboard until every worker is done or a stop is asked for. A stop is
    shown while the workers finish the sample in hand, then the final frame shows them
    stopped with their final counts."""
    started = time.monotonic()
    last = (started, [0] * len(workers))
    with Dashboard(live=config.dashboard) as dashboard:
        while True:
            _until_a_worker_ends(workers, stop_asked, WATCH_SECONDS)
            finished = stop_asked.is_set() or not any(w.is_alive() for w in workers)
            if finished:
                break
            now = time.monotonic()
            published = [shared.get(i, "published") for i in range(len(workers))]
            rates = [(p - q) / max(now - last[0], 1e-9) for p, q in zip(published, last[1])]
            if now - last[0] >= 2.0:
                last = (now, published)
            if dashboard.due():
                dashboard.update(snapshot(config, shared, rates, now - started))
        if stop_asked.is_set():
            rates = [0.0] * len(workers)
            dashboard.update(snapshot(config, shared, rates, time.monotonic() - started, stopping=True), final=True)
            shared.request_stop()
            _join(workers)
        elapsed = time.monotonic() - started
        means = [shared.get(i, "published") / max(elapsed, 1e-9) for i in range(len(workers))]  # over the run
        dashboard.update(snapshot(config, shared, means, elapsed, alive=[w.is_alive() for w in workers]), final=True)


def _until_a_worker_ends(workers: list, stop_asked: threading.Event, seconds: float) -> None:
    """Wait `seconds`, or less once a running worker ends: a run of --max-samples returns as its
    last worker exits, not up to half a second later (each test run of the daemon paid it)."""
    if stop_asked.is_set():
        return
    running = [w.sentinel for w in workers if w.is_alive()]
    if running:
        wait_for_any(running, timeout=seconds)


def snapshot(config: GenConfig, shared: Shared, rates: list[float], elapsed: float, stopping: bool = False,
             alive: list[bool] | None = None) -> GenSnapshot:
    """`stopping`: a stop was asked for and running workers are finishing their sample;
    `alive`: whether each worker process still runs (a dead one cannot be running)."""
    states = []
    for i in range(len(rates)):
        state = shared.get(i, "state")
        if state in (RUNNING, BACKING_OFF) and stopping:
            states.append("stopping")
        elif state in (RUNNING, BACKING_OFF) and alive is not None and not alive[i]:
            states.append("stopped")  # killed after JOIN_TIMEOUT
        else:
            states.append(STATE_NAMES[state])
    workers = [
        WorkerView(
            published=shared.get(i, "published"), evicted=shared.get(i, "evicted"),
            errors=shared.get(i, "errors"), rate=rates[i], state=states[i],
        )
        for i in range(len(rates))
    ]
    count, size, oldest, newest = spool_summary(config.spool)
    notes = ["disk full: workers back off and resume when space returns"] if any(
        w.state == STATE_NAMES[BACKING_OFF] for w in workers) else []
    if stopping:
        notes.append("stopping: each worker finishes the sample in hand")
    return GenSnapshot(
        elapsed=elapsed, workers=workers, spool=str(config.spool), spool_samples=count, spool_bytes=size,
        limit=config.limit, max_samples=config.max_samples, oldest_age=oldest, newest_age=newest,
        size=config.size, shape=config.shape, scene=config.scene.name, notes=notes,
    )


def spool_summary(spool: Path) -> tuple[int, int, float | None, float | None]:
    """Samples, bytes, and the ages (s) of the oldest and newest sample."""
    names = enumerate_spool(spool)
    total = 0
    for name in names:
        try:
            total += os.stat(os.path.join(spool, name)).st_size
        except FileNotFoundError:
            pass  # evicted while we looked
    if not names:
        return 0, 0, None, None
    now = time.time()
    return len(names), total, now - name_time(names[0]), now - name_time(names[-1])


def write_metadata(config: GenConfig) -> None:
    """Record the latest generator's config beside the samples (atomically). On a full disk the
    record is left as it was, with a warning: the workers wait for space as they always do, and a
    generator restarted onto a full disk must not need a hand (the soak found it exiting)."""
    from shared.sample import FORMAT, VERSION

    meta = {"format": FORMAT, "version": VERSION, "generator": config.to_dict(), "written": time.time()}
    try:
        write_json(config.spool / META_NAME, meta, indent=2, default=str)
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        log.warning("disk full under %s: its %s not updated; generating once there is space", config.spool, META_NAME)


def _install_stop_handlers(stop: threading.Event) -> dict:
    """SIGINT/SIGTERM only raise a flag that the watch loop polls: waiting on an Event
    that the handler sets can deadlock on the lock the interrupted wait holds."""
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, lambda *_: stop.set())
    return previous


def _restore_handlers(previous: dict) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def _join(workers: list) -> None:
    deadline = time.monotonic() + JOIN_TIMEOUT
    for w in workers:
        w.join(max(deadline - time.monotonic(), 0.1))
        if w.is_alive():
            log.warning("%s did not stop in time; killing it (publishing is atomic, nothing is torn)", w.name)
            w.kill()
            w.join()
