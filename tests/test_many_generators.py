"""Several `cuboidgen run` processes on one spool, as `docker compose up --scale generator=N` runs them.

The spool's stated bound is `limit + writers x evict_every`, where writers counts the
worker processes of every generator sharing it (shared/spool.py, docs/generator.md). Here three
daemons with 1, 1 and 2 workers (four writers) fill one spool while this test lists
it over and over, decoding everything listed.
"""
from __future__ import annotations

import hashlib
import os
import random
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

from cuboidgen.synth import sample_seed
from shared.sample import decode
from shared.spool import TMP_PREFIX, enumerate_spool, read_sample_bytes

LIMIT, EVICT_EVERY, SAMPLES, SEED = 40, 8, 400, 5  # 400 a daemon: ten times the limit, each writer evicting many times over
REREAD = 8  # names read again a listing
# (workers, --seed): two daemons share a seed, as scaled replicas given one CUBOIDGEN_SEED would.
DAEMONS = ((1, SEED), (1, SEED), (2, None))


def start(spool: Path, workers: int, seed: int | None) -> subprocess.Popen:
    script = Path(sys.executable).parent / "cuboidgen"
    assert script.exists(), "pip install -e . first: this test runs the installed cuboidgen"
    argv = [str(script), "run", "--spool", str(spool), "--limit", str(LIMIT), "--evict-every", str(EVICT_EVERY),
            "--workers", str(workers), "--size", "32", "--max-samples", str(SAMPLES), "--no-dashboard"]
    if seed is not None:
        argv += ["--seed", str(seed)]
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def writer_of(name: str) -> str:
    """host-pid-token: the one spool writer (a worker process) that published `name`."""
    return "-".join(name.split("-")[1:4])


def test_concurrent_generators_stay_within_the_bound_and_never_show_a_torn_sample(tmp_path):
    spool = tmp_path / "spool"
    writers = sum(workers for workers, _ in DAEMONS)
    bound = LIMIT + writers * EVICT_EVERY
    daemons = [start(spool, workers, seed) for workers, seed in DAEMONS]
    counts, decoded, vanished, corrupt, seen_writers, read_before = [], 0, 0, [], set(), set()
    rng = random.Random(0)
    seeds: dict[str, set[int]] = defaultdict(set)
    digests: dict[int, set[str]] = defaultdict(set)  # sample seed -> digests of what was published under it
    started = time.monotonic()
    deadline = started + 60
    try:
        while any(d.poll() is None for d in daemons) and time.monotonic() < deadline:
            names = enumerate_spool(spool) if spool.is_dir() else []
            if not names:  # the daemons are still starting: leave them the CPU
                time.sleep(0.05)
                continue
            counts.append(len(names))
            # Every writer's samples in the monitored spool (not all at once: on a loaded machine one
            # daemon may start when another has nearly finished, and the newest evict its samples).
            seen_writers |= {writer_of(n) for n in names}
            # The names not read yet, then a few read before (read again: a published name's bytes never
            # change), then list again: reading the whole listing each time left a loaded machine's monitor
            # a listing every ~50 reads, between two of which one writer's run came and was evicted.
            fresh = [n for n in names if n not in read_before]
            again = [n for n in names if n in read_before]
            for name in fresh + rng.sample(again, min(len(again), REREAD)):
                read_before.add(name)
                data = read_sample_bytes(spool, name)
                if data is None:  # evicted since the listing
                    vanished += 1
                    continue
                try:
                    sample = decode(data)
                except ValueError as exc:
                    corrupt.append(f"{name}: {exc}")
                    continue
                decoded += 1
                seeds[writer_of(name)].add(sample.seed)
                digests[sample.seed].add(hashlib.sha1(data).hexdigest())
    finally:
        for d in daemons:
            if d.poll() is None:
                d.kill()
            d.wait()
    assert all(d.returncode == 0 for d in daemons), [d.stderr.read().decode()[-500:] for d in daemons]
    seeded = {sample_seed(SEED, 0, k) for k in range(SAMPLES)}  # what a 1-worker daemon with --seed 5 draws
    same_seed = [w for w, s in seeds.items() if s <= seeded]
    twice = set.intersection(*(seeds[w] for w in same_seed)) if same_seed else set()
    print(f"\n{time.monotonic() - started:.1f} s, {len(DAEMONS)} daemons, {writers} writers: max {max(counts)} "
          f"samples listed (bound {bound}, limit {LIMIT}) over {len(counts)} listings; {decoded} samples decoded, "
          f"{vanished} vanished, {len(corrupt)} corrupt; {len(twice)} seeds seen from both same-seed writers")

    # The bound, and a monitor that really watched a full spool with every writer at work.
    assert not corrupt, corrupt[:3]
    assert max(counts) <= bound
    assert max(counts) >= LIMIT and len(seen_writers) == writers and len(counts) >= 20
    final = enumerate_spool(spool)
    # The spool can end a few below the limit (docs/generator.md, "The bound"): a writer that lists it
    # while another is between its publish and its eviction deletes that sample's match too, a dip of
    # up to one a writer, which only a later listing refills (one run here ended at 39 of 40).
    assert LIMIT - writers <= len(final) <= bound
    assert not [n for n in os.listdir(spool) if n.startswith(TMP_PREFIX)]  # clean exits leave no spares

    # Names never collide: every worker is a writer of its own (host, pid, random token),
    # even where two daemons were given the same --seed ...
    assert len(seeds) == writers and len(same_seed) == 2
    # ... but their contents do: the same seed draws the same samples, bit for bit, which is
    # why scaled generators are given no seed (docker-compose.yml). An unseeded daemon draws
    # a run seed of its own, so its samples share no seed with anyone's.
    assert twice and all(len(digests[s]) == 1 for s in twice)
    unseeded = set().union(*(s for w, s in seeds.items() if w not in same_seed))
    assert unseeded and not unseeded & seeded
