"""Benchmarks: generation and spool-read throughput, with baselines run in the same process.

Figures are medians over repeats (this machine is shared and noisy). Ratios
compare against a baseline measured in the same run:

* generation: published samples/s on one core, against drawing and encoding only; and
  for every scene preset and shape class, and the daemon with one worker into a capped spool;
* spool read: read + decode + collate into torch tensors on one core, against what
  a user would otherwise write: generating each sample on the fly inside torch
  DataLoader workers (all cores).
"""
from __future__ import annotations

import logging
import os
import statistics
import tempfile
import time

from pathlib import Path

import cv2
import numpy as np

from cuboidgen.config import PAPER, SCENES, GenConfig, SceneConfig
from cuboidgen.occluders import OccluderLibrary
from shared.threads import threads_held
from cuboidgen.synth import make_sample
from shared.sample import collate, decode_packed, encode
from shared.spool import SpoolWriter, enumerate_spool, read_sample_bytes

TARGETS = {"generate_per_core": 2000.0, "bytes_per_sample": 20 * 1024, "read_one_core": 20000.0, "read_over_generate": 10.0}


def rate(count: int, seconds: float) -> float:
    return count / max(seconds, 1e-9)


def timed(fn, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def bench_generate(size: int, samples: int, repeats: int, library, where: str = ".", shape: str = "box",
                   scene: SceneConfig = PAPER) -> dict:
    """One core: draw + encode only, and draw + encode + publish into a spool at its cap."""
    # one core's pace; the caller's count restored after: a process that goes on to fit masks keeps
    # its own (OpenCV's sums, and so a fit's last bits, follow it)
    with threads_held(cv2.getNumThreads, cv2.setNumThreads):
        return _bench_generate(size, samples, repeats, library, where, shape, scene)


def _bench_generate(size: int, samples: int, repeats: int, library, where: str, shape: str,
                    scene: SceneConfig) -> dict:
    seeds = iter(range(10**9))
    draw = lambda: [encode(make_sample(shape, scene, size, next(seeds), library)) for _ in range(samples)]  # noqa: E731
    with tempfile.TemporaryDirectory(dir=where, prefix=".bench-") as spool, SpoolWriter(Path(spool), limit=samples) as writer:
        def publish():
            for _ in range(samples):
                writer.publish(encode(make_sample(shape, scene, size, next(seeds), library)))

        publish()  # untimed: fill the spool to its cap, so every timed publish also evicts, as a running daemon's does
        draw_times, publish_times = [], []
        for _ in range(repeats):  # interleaved so both see the same machine load
            draw_times += timed(draw, 1)
            publish_times += timed(publish, 1)
        sizes = [os.path.getsize(os.path.join(spool, n)) for n in enumerate_spool(Path(spool))]
    generate_only = rate(samples, statistics.median(draw_times))
    published = rate(samples, statistics.median(publish_times))
    return {
        "size": size, "shape": shape, "scene": scene.name, "samples_per_repeat": samples, "repeats": repeats,
        "generate_only_per_s": generate_only, "published_per_s_per_core": published,
        "publish_vs_generate_only": published / generate_only,
        "bytes_per_sample_mean": float(np.mean(sizes)), "bytes_per_sample_max": int(max(sizes)),
    }


def bench_scenes(size: int, samples: int, repeats: int, library, where: str = ".") -> list[dict]:
    """`bench_generate` for every scene preset and shape class: a generator worker's pace at each
    (issue 29: when a GPU outruns the generator, the spool's reuse is the answer, not a faster one)."""
    return [bench_generate(size, samples, repeats, library, where, shape, scene)
            for scene in SCENES.values() for shape in ("box", "twobox")]


def bench_stages(size: int, samples: int, library, where: str = ".") -> dict:
    """Where a sample's time goes, one core: per-sample medians (us) of each stage of
    `make_sample` (box, paper scene), of encoding, and of publishing into a spool at
    its cap, over `2 * samples` samples."""
    from cuboidgen.noise import roughen
    from cuboidgen.occlusion import occlude
    from shared.raster import rasterize
    from cuboidgen.scene import draw_view, uniform
    from cuboidgen.synth import seeded, silhouette_box
    from shared.shapes import get_shape

    cv2.setNumThreads(1)
    geometry, clock = get_shape("box"), time.perf_counter
    stages = ("view", "raster", "occlusion", "contour_noise", "make_sample", "encode", "publish")
    times: dict[str, list[float]] = {k: [] for k in stages}
    with tempfile.TemporaryDirectory(dir=where, prefix=".bench-") as spool, SpoolWriter(Path(spool), limit=samples) as writer:
        for seed in range(samples):  # fill the spool to its cap: time publishing in its steady state
            writer.publish(encode(make_sample("box", PAPER, size, seed, library)))
        for seed in range(samples, 3 * samples):
            t0 = clock()
            rng = seeded(seed)
            view = draw_view(geometry, PAPER, size, rng)
            t1 = clock()
            clean = rasterize(geometry, view.keypoints, size)
            t2 = clock()
            occluded, _ = occlude(clean, library, PAPER, rng, box=silhouette_box(view.keypoints, size))
            t3 = clock()
            amount = uniform(rng, PAPER.contour_noise) * size / 256
            roughen(occluded, amount, uniform(rng, PAPER.noise_wavelength) * size / 256, rng)
            t4 = clock()
            sample = make_sample("box", PAPER, size, seed, library)
            t5 = clock()
            data = encode(sample)
            t6 = clock()
            writer.publish(data)
            t7 = clock()
            for stage, seconds in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6)):
                times[stage].append(seconds)
    return {"size": size, "samples": 2 * samples, **{f"{k}_us": statistics.median(v) * 1e6 for k, v in times.items()}}


def bench_daemon(size: int, samples: int, workers: int, where: str = ".", limit: int | None = None) -> dict:
    """The real daemon with `workers` workers, process start-up included, into a spool capped at
    `limit` samples (default `samples`: it never evicts; fewer: it evicts as a running daemon does)."""
    from cuboidgen.daemon import run

    limit = samples if limit is None else limit
    with tempfile.TemporaryDirectory(dir=where, prefix=".bench-") as spool:
        config = GenConfig(spool=Path(spool), limit=limit, max_samples=samples, workers=workers, size=size,
                           seed=0, dashboard=False)
        start = time.perf_counter()
        run(config)
        seconds = time.perf_counter() - start
    return {"workers": workers, "samples": samples, "limit": limit, "published_per_s": rate(samples, seconds),
            "published_per_s_per_worker": rate(samples, seconds) / workers}


def bench_read(size: int, samples: int, batch: int, repeats: int, library, where: str = ".") -> dict:
    """One core: enumerate, read, decode and collate into torch tensors, every epoch anew."""
    import torch

    with tempfile.TemporaryDirectory(dir=where, prefix=".bench-") as tmp:
        spool = Path(tmp)
        with SpoolWriter(spool, limit=0) as writer:
            for seed in range(samples):
                writer.publish(encode(make_sample("box", PAPER, size, seed, library)))

        def epoch(unpack: bool):
            names = enumerate_spool(spool)
            for start in range(0, len(names), batch):
                records = [decode_packed(read_sample_bytes(spool, n)) for n in names[start : start + batch]]
                tensors = {k: torch.from_numpy(v) for k, v in collate(records, unpack=unpack).items()}
                assert tensors["keypoints"].shape[0] == len(records)

        epoch(True)  # warm the page cache: a trainer reads a spool the generator just wrote
        unpacked = timed(lambda: epoch(True), repeats)
        packed = timed(lambda: epoch(False), repeats)
    return {
        "size": size, "samples": samples, "batch": batch, "repeats": repeats,
        "read_unpacked_per_s": rate(samples, statistics.median(unpacked)),
        "read_packed_per_s": rate(samples, statistics.median(packed)),
    }


class OnTheFly:
    """What a user would otherwise write: a Dataset that generates each sample when asked."""

    def __init__(self, size: int, count: int):
        self.size, self.count, self.library = size, count, None

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int):
        import torch

        if self.library is None:  # built once per DataLoader worker
            cv2.setNumThreads(1)
            self.library = OccluderLibrary.builtin()
        s = make_sample("box", PAPER, self.size, index, self.library)
        return (torch.from_numpy(s.noisy.view(np.uint8)), torch.from_numpy(s.clean.view(np.uint8)),
                torch.from_numpy(s.keypoints.astype(np.float32)))


# A batch that takes longer than this is a stuck worker, not a slow one (a 256 px batch of 64 takes
# about a second on one core): the stage is then given up, and says so, instead of waiting forever.
ON_THE_FLY_TIMEOUT_S = 120.0


def bench_on_the_fly(size: int, samples: int, batch: int, workers: int, repeats: int,
                     timeout: float = ON_THE_FLY_TIMEOUT_S) -> dict:
    """DataLoader workers generating samples as they are asked, started by spawn, not fork: the
    benchmarks before this one ran OpenCV's thread pool in this process, and a forked worker
    inherits that pool's locks mid-use, so its first cv2 call (`setNumThreads`) waits forever
    on a condition no thread will signal (seen: `cuboidgen bench` hung with no output)."""
    from torch.utils.data import DataLoader

    loader = DataLoader(OnTheFly(size, samples), batch_size=batch, num_workers=workers,
                        persistent_workers=workers > 0, multiprocessing_context="spawn" if workers else None,
                        timeout=timeout if workers else 0)
    try:
        list(loader)  # start the workers and build their libraries outside the timing
        times = timed(lambda: list(loader), repeats)
    except RuntimeError as exc:  # DataLoader's own timeout: a batch not back within `timeout` s
        if "timed out" not in str(exc):
            raise
        logging.getLogger(__name__).warning(
            "on-the-fly stage given up: a DataLoader worker sent no batch within %g s", timeout)
        return {"workers": workers, "samples": samples, "on_the_fly_per_s": None, "timed_out_s": timeout}
    return {"workers": workers, "samples": samples, "on_the_fly_per_s": rate(samples, statistics.median(times))}


def run_benchmarks(size: int = 256, samples: int = 400, repeats: int = 5, batch: int = 64, where: str = ".") -> dict:
    """Every benchmark in one process, with the ratios the targets are stated in.

    Spools are made under `where`: measure on the filesystem the real spool lives on
    (file creation cost differs tenfold between mounts of one machine)."""
    library = OccluderLibrary.builtin()
    cores = os.cpu_count() or 1
    generate = bench_generate(size, samples, repeats, library, where)
    read = bench_read(size, max(samples * 5, 1000), batch, repeats, library, where)
    fly = bench_on_the_fly(size, samples, batch, cores, max(repeats // 2, 2))
    daemon = bench_daemon(size, samples * 4, cores, where)
    scenes = bench_scenes(size, samples, max(repeats // 2, 2), library, where)
    capped = bench_daemon(size, samples * 20, 1, where, limit=samples * 5)  # 8,000 samples into 2,000 by default
    results = {
        "machine": {"cores": cores, "cpu": _cpu_name(), "spool_dir": str(Path(where).resolve())},
        "generate": generate, "daemon": daemon, "read": read, "on_the_fly": fly,
        "scenes": scenes, "daemon_one_worker_capped": capped,
        "ratios": {
            "read_unpacked_over_generate_per_core": read["read_unpacked_per_s"] / generate["published_per_s_per_core"],
            "read_unpacked_over_on_the_fly": per(read["read_unpacked_per_s"], fly["on_the_fly_per_s"]),
            "read_packed_over_on_the_fly": per(read["read_packed_per_s"], fly["on_the_fly_per_s"]),
        },
        "targets": TARGETS,
    }
    print_table(results)
    return results


def per(rate: float, baseline: float | None) -> float | None:
    """`rate` over `baseline`; None where the baseline was not measured (a stage that timed out)."""
    return None if baseline is None else rate / baseline


def print_table(r: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    g, d, rd, f = r["generate"], r["daemon"], r["read"], r["on_the_fly"]
    t = Table("measure", "median", "target", title=f"cuboidgen bench, {g['size']}x{g['size']}, {r['machine']['cores']} cores")
    t.add_row("generate + encode, 1 core", f"{g['generate_only_per_s']:,.0f} /s", "")
    t.add_row("generate + publish, 1 core", f"{g['published_per_s_per_core']:,.0f} /s", f">= {TARGETS['generate_per_core']:,.0f} /s")
    t.add_row(f"daemon, {d['workers']} workers (start-up included)", f"{d['published_per_s']:,.0f} /s", "")
    c = r["daemon_one_worker_capped"]
    t.add_row(f"daemon, 1 worker, {c['samples']:,} samples into {c['limit']:,} (start-up included)",
              f"{c['published_per_s']:,.0f} /s", "")
    for scene in r["scenes"]:
        t.add_row(f"generate + publish, 1 core: {scene['scene']} {scene['shape']}",
                  f"{scene['published_per_s_per_core']:,.0f} /s", "")
    t.add_row("bytes per sample (mean / max)", f"{g['bytes_per_sample_mean']:,.0f} / {g['bytes_per_sample_max']:,}", "<= 20,480")
    t.add_row("spool read -> tensors, 1 core (unpacked)", f"{rd['read_unpacked_per_s']:,.0f} /s", ">= 20,000 /s")
    t.add_row("spool read -> tensors, 1 core (packed bits)", f"{rd['read_packed_per_s']:,.0f} /s", "")
    fly = f"{f['on_the_fly_per_s']:,.0f} /s" if f["on_the_fly_per_s"] is not None else f"timed out ({f['timed_out_s']:g} s)"
    t.add_row(f"on the fly in DataLoader, {f['workers']} workers", fly, "baseline")
    for name, value in r["ratios"].items():
        shown = f"{value:,.1f}x" if value is not None else "no baseline"
        t.add_row(name.replace("_", " "), shown, ">= 10x" if "generate" in name else "")
    Console(stderr=True).print(t)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"



