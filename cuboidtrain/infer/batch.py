"""`cuboidtrain infer` over many inputs, in labelled phases: resume from OUT, fit (in this process or
a pool), store each input's records as it completes, report progress, summarise.

The pieces have a module each: `inputs` (what to fit), `storage` (where a mask is read from: a
local path or an fsspec URL), `records` (the records, the JSONL file and its resume), `pool`
(where fits run on this machine), `cluster` (on a Dask cluster, imported only for `--cluster`),
`reporting` (what the user sees: a line per record, the progress, a total). What travels between them is typed: each input's outcomes
(`Fit`, `FitFailure`), made into records only by `records` as they are written.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable, Sequence
from contextlib import closing, nullcontext
from dataclasses import dataclass
from pathlib import Path

from cuboidtrain.fit.fitter import FitFailure, Outcome
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.pool import fit_groups
from cuboidtrain.infer.reporting import Reporter, Tally
from cuboidtrain.infer.records import RecordStore, to_records

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Batch:
    """One infer run's inputs and where its fits run and go."""

    inputs: tuple[str, ...]  # in input order; a record's "index" is a position here
    checkpoints: tuple[Path, ...]  # what a pool's workers load
    options: FitOptions
    workers: int = 1  # 1: in this process, with the caller's Fitter
    jsonl: Path | None = None  # the record store, resumed when it exists
    keep: bool = True  # return the outcomes (for --json's list); a city's run keeps none in memory
    cluster: str | None = None  # a Dask scheduler's address, or "local" (`workers` processes here); None: no cluster

    def indexed(self) -> list[str]:
        """The inputs a record's (and a per-fit writer's) index counts: each once with a record
        store (it keys records by input, `unique`), else as given."""
        return list(dict.fromkeys(self.inputs)) if self.jsonl else list(self.inputs)


def run_batch(batch: Batch, fitter, console, explain: Callable | None = None,
              stop=()) -> tuple[list[Outcome | dict], Tally]:
    """The outcomes of the inputs in input order (when `batch.keep`; an input OUT already held
    by its records, as read back: `records.to_record` passes them on) and the run's Tally.
    Once `stop` is true (`stopping.Stop`: Ctrl-C, SIGTERM) no input starts: the outcomes are
    those fitted by then, and the Tally says what stopped it."""
    inputs = unique(batch.inputs) if batch.jsonl else list(batch.inputs)
    with RecordStore(batch.jsonl, batch.options) if batch.jsonl else nullcontext() as store:
        # resume: the inputs OUT already holds are counted, not fitted again
        held = defaultdict(list)
        for record in store.records if store else ():
            held[record["input"]].append({k: v for k, v in record.items() if k != "index"})
        tally = Tally(total=len(inputs))
        kept = {}
        jobs = []
        for index, path in enumerate(inputs):
            if path in held:
                tally.resume(held[path])
                kept[index] = held[path] if batch.keep else None
            else:
                jobs.append((index, path))
        if tally.resumed:
            log.info("%s holds %d of the %d inputs; fitting the other %d", batch.jsonl, tally.resumed,
                     len(inputs), len(jobs))
        # fit, store and show each input's outcomes as they complete
        groups = fitted(batch, jobs, fitter, explain, stop)
        elsewhere = batch.workers > 1 or batch.cluster is not None
        with Reporter(tally, console, inputs, batch.options.shapes) as reporter, closing(groups):
            for index, outcomes in groups:
                if elsewhere:
                    say_warnings(outcomes)
                records = to_records(outcomes, batch.options)  # once: OUT's lines and the answers shown
                if store:
                    store.write(index, records)
                if batch.keep:
                    kept[index] = outcomes
                reporter.add(records)
                if stop and batch.cluster is not None:  # a pool finishes its inputs in hand; a cluster's are dropped
                    break
            if stop and tally.resumed + tally.done < tally.total:
                tally.stopped = stop.name
    outcomes = [o for index in sorted(kept) for o in kept[index]] if batch.keep else []
    return outcomes, tally


def fitted(batch: Batch, jobs: list[tuple[int, str]], fitter, explain: Callable | None, stop=()):
    """The jobs' (index, outcomes) from wherever `batch` says fits run."""
    if batch.cluster is None:
        return fit_groups(jobs, fitter, batch.checkpoints, batch.options, batch.workers, explain, stop)
    from cuboidtrain.infer.cluster import cluster_groups  # Dask only when asked: an optional extra

    return cluster_groups(jobs, batch.checkpoints, batch.options, batch.cluster, batch.workers)


def say_warnings(outcomes: Sequence[Outcome]) -> None:
    """Log an input's warnings and failure here, as `Fitter.outcomes` logs them in this process, for
    outcomes fitted in another: a pool's worker logs errors only (its lines would tear the progress
    bar, which this process's log handler keeps whole), a cluster's logs where it runs."""
    for outcome in outcomes:
        if isinstance(outcome, FitFailure):
            log.warning("%s", outcome.reason)
        else:
            for warning in outcome.warnings:
                log.warning("%s: %s", outcome.input, warning)


def unique(inputs: Sequence[str]) -> list[str]:
    """The inputs once each, in first-seen order: OUT keys its records by input."""
    seen = list(dict.fromkeys(inputs))
    if len(seen) < len(inputs):
        log.warning("%d inputs given more than once: each is fitted once", len(inputs) - len(seen))
    return seen
