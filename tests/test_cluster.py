"""`infer --cluster` (cuboidtrain/infer/cluster.py): a local Dask cluster of two workers stores the
records of the single-process run, and resumes its store as the local pool does; without the
extra, `--cluster` is a one-line error naming it. The test extra brings Dask (`.[test]` holds
`dask[distributed]`), so these tests run wherever the suite does, never skipped."""
from __future__ import annotations

import os
import sys

import pytest
import torch
from rich.console import Console

from cuboidtrain.infer.batch import Batch, run_batch
from cuboidtrain.fit.fitter import Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.records import read_records, to_records
from cuboidtrain.models.zoo import default_checkpoints
from shared.errors import UsageError
from tests.conftest import write_mask_pngs

OPTIONS = FitOptions(device="cpu")


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> list[str]:
    """12 generated masks of 64 to 128 px, box and twobox."""
    return write_mask_pngs(tmp_path_factory.mktemp("masks"), 12)


def run(paths, **batch) -> list[dict]:
    """`run_batch`'s records, this process at one torch thread (as each cluster worker runs)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        checkpoints = default_checkpoints(None, OPTIONS.shapes)
        fitter = Fitter.from_files(checkpoints, OPTIONS)
        outcomes = run_batch(Batch(tuple(paths), tuple(checkpoints), OPTIONS, **batch), fitter,
                             Console(file=open(os.devnull, "w")))[0]
        return to_records(outcomes, OPTIONS)
    finally:
        torch.set_num_threads(threads)


def test_a_local_cluster_of_two_workers_stores_the_records_of_one_process(tmp_path, masks):
    out = tmp_path / "out.jsonl"
    run(masks[:5], jsonl=out)  # a first run (in this process: one cluster start is enough), as if killed after 5
    assert [r["index"] for r in read_records(out)] == list(range(5))
    records = run(masks, workers=2, jsonl=out, cluster="local")  # resumed: the other 7 on the cluster
    stored = read_records(out)
    assert [r["index"] for r in stored] == list(range(12))  # each input once
    expected = run(masks)
    assert [{k: v for k, v in r.items() if k != "index"} for r in stored] == expected
    assert records == expected


def test_cluster_without_dask_is_a_one_line_error_naming_the_extra(monkeypatch, masks):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(UsageError, match=r"pip install 'cuboid-fit\[cluster\]'") as error:
        run(masks[:1], cluster="tcp://127.0.0.1:8786")
    assert "\n" not in str(error.value)
