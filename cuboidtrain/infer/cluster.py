"""Fitting many inputs on a Dask cluster (`cuboidtrain infer --cluster ADDRESS`), the optional extra
`pip install 'cuboid-fit[cluster]'`.

`cluster_groups` yields `(index, outcomes)` per input as fits complete, as `pool.fit_groups` does,
so `batch.run_batch` stores, resumes and reports them the same way. ADDRESS `local` starts a
LocalCluster on 127.0.0.1 with `workers` processes of one thread; `tcp://host:8786` joins a running
scheduler. Inputs go out as chunks of paths (`pool.CHUNK`), at most two chunks a worker thread in
flight: the workers read the masks themselves, so every worker must see the same paths (a shared
file system) or reach the same URLs (an object store: `storage`). Each worker thread builds its
Fitter once, on its first chunk, and keeps it for every later chunk of the same models and options.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

from cuboidtrain import allocator
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.pool import CHUNK, Group, fit_one
from shared.errors import UsageError

LOCAL = "local"
_local = threading.local()  # a worker thread's Fitter, keyed by what built it


def cluster_groups(jobs: Sequence[tuple[int, str]], checkpoints: Sequence[Path], options: FitOptions,
                   address: str, workers: int = 1) -> Iterator[Group]:
    """Each job's (index, outcomes), fitted on the cluster at `address`, in completion order."""
    distributed = require_distributed(address)
    logging.getLogger("distributed").setLevel(logging.WARNING)  # its INFO lines would drown the progress
    cluster = None
    if address == LOCAL:
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None)
    client = distributed.Client(cluster or address)
    try:
        yield from _stream(client, distributed, jobs, [str(c) for c in checkpoints], options)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def require_distributed(address: str):
    """The `distributed` module, or a one-line UsageError naming the extra."""
    try:
        import distributed
    except ImportError:
        raise UsageError(f"--cluster {address}: Dask is not installed; expected the cluster extra: "
                         f"pip install 'cuboid-fit[cluster]'") from None
    return distributed


def _stream(client, distributed, jobs, checkpoints: list[str], options: FitOptions) -> Iterator[Group]:
    threads = max(1, sum(client.nthreads().values()))
    chunks = iter([list(jobs[i:i + CHUNK]) for i in range(0, len(jobs), CHUNK)])
    running = distributed.as_completed()
    pending = set()

    def submit() -> bool:
        chunk = next(chunks, None)
        if chunk is None:
            return False
        future = client.submit(_fit_chunk, chunk, checkpoints, options, pure=False)
        pending.add(future)
        running.add(future)
        return True

    try:
        while len(pending) < 2 * threads and submit():
            pass
        for future in running:
            pending.discard(future)
            yield from future.result()
            submit()
    finally:
        for future in pending:
            future.cancel()


def _fit_chunk(chunk: list[tuple[int, str]], checkpoints: list[str], options: FitOptions) -> list[Group]:
    """On a worker: the chunk's groups, with this thread's Fitter (built on its first chunk)."""
    fitter = _fitter(checkpoints, options)
    return [fit_one(fitter, index, path) for index, path in chunk]


def _fitter(checkpoints: list[str], options: FitOptions):
    key = (tuple(checkpoints), options)
    if getattr(_local, "key", None) != key:
        import torch

        from cuboidtrain.fit.fitter import Fitter

        torch.set_num_threads(1)  # one thread a fit, as the local pool's workers; one process a core
        undo_nanny_trim()
        _local.fitter, _local.key = Fitter.from_files(checkpoints, options), key
    return _local.fitter


def undo_nanny_trim() -> None:
    """Undo, in this worker, the MALLOC_TRIM_THRESHOLD_=65536 a Dask nanny gives its workers
    (`distributed.nanny.pre-spawn-environ`). It turns off glibc's adaptive thresholds: every
    buffer of a fit over 128 KB is then mmap'ed, freed to the kernel and faulted in again on
    the next fit. Measured: 200 fits 5.4 to 5.8 s with it (1.2 to 1.4 million page faults, about
    2 s in the kernel), 3.2 to 3.3 s after this (BENCHMARKS.md). glibc only; elsewhere nothing to undo."""
    allocator.keep_freed_memory(32 * 1024 * 1024, 64 * 1024 * 1024)  # glibc's adaptive ceiling; 64 MB kept at the top
