"""Fitting many inputs on one machine: in this process, or in `workers` processes, each with its own
Fitter (models loaded once per worker) and one torch thread.

`fit_groups` yields `(index, records)` per input as fits complete: in input order in this
process, in completion order from a pool (the index says which input). Inputs go to the
workers in chunks of `CHUNK`, at most two chunks a worker in flight, so a kill loses at most
those and memory does not grow with the run. A per-fit writer (`explain`: `--mesh`'s files) goes
to each worker as a pickled copy and writes there.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path

from cuboidtrain.fit.options import FitOptions

CHUNK = 4  # inputs a task: at ~16 ms a mask, enough to hide the pickling, little lost to a kill
Group = tuple[int, list[dict]]  # (input index, its records)

_fitter = None  # the worker's own Fitter, built once by `_start_worker`
_explain = None  # and its per-fit writer (a pickled copy of the parent's: `--mesh`), or None


def fit_one(fitter, index: int, path: str, explain: Callable | None = None) -> Group:
    """Input `index`'s records (`Fitter.records` on it alone; `explain` sees the run's index)."""
    call = None if explain is None else (lambda _i, p, f: explain(index, p, f))
    return index, list(fitter.records([path], explain=call))


def fit_groups(jobs: Sequence[tuple[int, str]], fitter=None, checkpoints: Sequence[Path] = (),
               options: FitOptions | None = None, workers: int = 1,
               explain: Callable | None = None) -> Iterator[Group]:
    """Each job's (index, records): with `fitter` in this process when `workers` is 1, else in a
    pool whose workers build theirs from `checkpoints` and `options`."""
    if workers <= 1:
        for index, path in jobs:
            yield fit_one(fitter, index, path, explain)
        return
    yield from _pooled(jobs, list(map(str, checkpoints)), options, workers, explain)


def _pooled(jobs, checkpoints, options, workers, explain: Callable | None = None) -> Iterator[Group]:
    chunks = [list(jobs[i:i + CHUNK]) for i in range(0, len(jobs), CHUNK)]
    context = get_context("spawn")  # fork after torch has threads is unsafe
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker,
                             initargs=(checkpoints, options, os.getpid(), explain)) as pool:
        pending, queued = set(), iter(chunks)
        try:
            while True:
                while len(pending) < 2 * workers and (chunk := next(queued, None)) is not None:
                    pending.add(pool.submit(_fit_chunk, chunk))
                if not pending:
                    return
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    yield from future.result()
        finally:
            for future in pending:
                future.cancel()


def _start_worker(checkpoints: list[str], options: FitOptions, parent: int, explain: Callable | None = None) -> None:
    import logging

    import torch

    from cuboidtrain.fit.fitter import Fitter

    global _fitter, _explain
    # A spawned worker writes to the terminal behind the parent's progress bar: on a 20,000-mask
    # run its warnings tore the bar every few lines. A fit's warnings are in its record: errors only here.
    logging.basicConfig(level=logging.ERROR, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    _fitter = Fitter.from_files(checkpoints, replace(options))
    _explain = explain
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()


def _exit_with(parent: int) -> None:
    """A worker whose parent was killed (kill -9 leaves the pool no time to stop it) exits."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(0)


def _fit_chunk(chunk: list[tuple[int, str]]) -> list[Group]:
    return [fit_one(_fitter, index, path, _explain) for index, path in chunk]
