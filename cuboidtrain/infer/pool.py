"""Fitting many inputs on one machine: in this process, or in `workers` processes, each with its own
Fitter (models loaded once per worker) and one torch thread.

`fit_groups` yields `(index, outcomes)` per input as fits complete: in input order in this
process, in completion order from a pool (the index says which input). The outcomes are typed
(`Fit`, `FitFailure`), their explanations' arrays left behind (`Fitter.outcomes`), so a pool
sends back about as much as their records would weigh: records are made where they are
written (`records.to_record`). Inputs go to the workers in chunks of `CHUNK` paths (each
worker reads its own masks), at most two chunks a worker in flight, so a kill loses at most
those and memory does not grow with the run. A per-fit writer (`explain`: `--mesh`'s files)
goes to each worker as a pickled copy and writes there.

The workers are forked from a fork server that has imported torch and the Fitter once
(`warm_up`, called by `infer` before this process imports torch itself, so the two imports
run side by side): each worker then starts in a few hundredths of a second instead of
importing torch again (about a second a worker, on a run's critical path). The server forks
before any torch thread exists, which keeps fork safe; this process, which has torch
threads, never forks.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import replace
from multiprocessing import get_all_start_methods, get_context
from pathlib import Path
from typing import TYPE_CHECKING

from cuboidtrain.fit.options import FitOptions

if TYPE_CHECKING:  # the fitter imports torch, which `warm_up` must come before
    from cuboidtrain.fit.fitter import Outcome

PARENT_LOOK_S = 0.2  # how often a worker looks whether `infer` still runs: a /proc read, a killed run's workers gone within it
CHUNK = 4  # inputs a task: at ~16 ms a mask, enough to hide the pickling, little lost to a kill
Group = tuple[int, list["Outcome"]]  # (input index, its outcomes)

_fitter = None  # the worker's own Fitter, built once by `_start_worker`
_explain = None  # and its per-fit writer (a pickled copy of the parent's: `--mesh`), or None


def fit_one(fitter, index: int, path: str, explain: Callable | None = None) -> Group:
    """Input `index`'s outcomes (`Fitter.outcomes` on it alone; `explain` sees the run's index)."""
    call = None if explain is None else (lambda _i, p, f: explain(index, p, f))
    return index, list(fitter.outcomes([path], explain=call))


def fit_groups(jobs: Sequence[tuple[int, str]], fitter=None, checkpoints: Sequence[Path] = (),
               options: FitOptions | None = None, workers: int = 1,
               explain: Callable | None = None, stop=()) -> Iterator[Group]:
    """Each job's (index, outcomes): with `fitter` in this process when `workers` is 1, else in a
    pool whose workers build theirs from `checkpoints` and `options`. Once `stop` is true
    (`stopping.Stop`) no job starts; those in hand finish and are yielded."""
    if workers <= 1:
        for index, path in jobs:
            if stop:
                return
            yield fit_one(fitter, index, path, explain)
        return
    yield from _pooled(jobs, list(map(str, checkpoints)), options, workers, explain, stop)


PRELOAD = ["torch", "cuboidtrain.fit.fitter"]  # what the fork server imports for every worker


ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def warm_up(workers: int) -> None:
    """Start the fork server the workers come from (it imports torch and the Fitter), so that
    it does while this process reads its inputs and loads its own models. Nothing for 1 worker."""
    if workers > 1:
        worker_context()


def worker_context():
    """Never fork this process (torch has threads here): a fork server where there is one, else
    spawn (Windows), each worker importing torch itself. The server is started once a process,
    with one thread for OpenMP and BLAS: numpy's BLAS would otherwise start a thread a core at
    import, and a fork copies no thread but the caller. Its workers run one thread each anyway."""
    if "forkserver" not in get_all_start_methods():
        return get_context("spawn")
    from multiprocessing import forkserver

    context = get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    saved = {name: os.environ.get(name) for name in ONE_THREAD}
    os.environ.update(ONE_THREAD)  # what the server inherits, only while it starts
    try:
        with _stdout_to_devnull(), _ctrl_c_ignored():
            forkserver.ensure_running()
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name)
            else:
                os.environ[name] = value
    return context


@contextmanager
def _stdout_to_devnull():
    """The fork server (and so every worker) gets /dev/null as its stdout, which only this process
    writes (the JSON records): otherwise the server, which outlives `infer` by a moment as it
    shuts down, holds a pipe's write end open, and `infer --json - | jq` waited about 0.5 s for
    its end of file. stderr stays shared: a worker's fatal error still reaches the terminal."""
    sys.stdout.flush()
    kept, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(kept, 1)
        os.close(kept)
        os.close(devnull)


@contextmanager
def _ctrl_c_ignored():
    """The fork server, and so every worker, starts with Ctrl-C ignored (an ignored signal stays
    ignored across exec, and the server hands its own disposition down): Ctrl-C reaches the whole
    process group, and this process decides (`stopping.Stop`). Without it a Ctrl-C while the
    server imports torch printed its traceback, and one while a worker started broke the pool."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _pooled(jobs, checkpoints, options, workers, explain: Callable | None = None, stop=()) -> Iterator[Group]:
    chunks = [list(jobs[i:i + CHUNK]) for i in range(0, len(jobs), CHUNK)]
    context = worker_context()
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker,
                             initargs=(checkpoints, options, os.getpid(), explain)) as pool:
        pending, queued = set(), iter(chunks)
        try:
            while True:
                while not stop and len(pending) < 2 * workers and (chunk := next(queued, None)) is not None:
                    pending.add(pool.submit(_fit_chunk, chunk))
                if stop:  # the chunks no worker has taken yet never start
                    pending = {future for future in pending if not future.cancel()}
                if not pending:
                    return
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    try:
                        groups = future.result()
                    except BrokenProcessPool:
                        if stop:  # Ctrl-C reached a worker still starting, before it could leave it to us
                            return
                        raise
                    yield from groups
        finally:
            for future in pending:
                future.cancel()


def _start_worker(checkpoints: list[str], options: FitOptions, parent: int, explain: Callable | None = None) -> None:
    import logging

    import torch

    from cuboidtrain.fit.fitter import Fitter
    from cuboidtrain.infer.stopping import leave_signals_to_parent

    global _fitter, _explain
    leave_signals_to_parent()
    # A spawned worker writes to the terminal behind the parent's progress bar: on a 20,000-mask
    # run its warnings tore the bar every few lines. A fit's warnings are in its record: errors only here.
    logging.basicConfig(level=logging.ERROR, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    _fitter = Fitter.from_files(checkpoints, replace(options))
    _explain = explain
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()


def _exit_with(parent: int) -> None:
    """A worker whose parent was killed (kill -9 leaves the pool no time to stop it) exits. Its
    own parent is the fork server, which lives as long as any worker does: watch `infer`'s process."""
    while _alive(parent):
        time.sleep(PARENT_LOOK_S)
    os._exit(0)


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, killed and not yet reaped, does not)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except FileNotFoundError:
        if os.path.isdir("/proc/self"):
            return False
    except OSError:
        return False
    try:  # no /proc (macOS): signal 0 only asks whether it exists
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def _fit_chunk(chunk: list[tuple[int, str]]) -> list[Group]:
    return [fit_one(_fitter, index, path, _explain) for index, path in chunk]
