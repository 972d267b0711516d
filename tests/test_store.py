"""The infer records and their JSONL store (cuboidtrain/infer/records.py): a Fit's and a FitFailure's
record, round trip, a torn last line cut off on resume, a file that is not a record store refused,
a full disk keeping every whole record."""
from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from cuboidtrain.fit.fitter import Fit, FitFailure
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer import records as store_module
from cuboidtrain.infer.records import RecordStore, read_records, to_record
from shared.errors import UsageError

COMPONENTS = FitOptions(all_components=True)


def outcome(path: str, shape: str | None = "box", component: int | None = None) -> Fit | FitFailure:
    """A fit of `shape` (a FitFailure for None) of input `path`."""
    if shape is None:
        return FitFailure(path, "cannot read")
    return Fit(shape=shape, keypoints=np.arange(16.0).reshape(8, 2), ratios={"depth_height": 0.5, "width_height": 1.0},
               confidence=0.875, refine_steps=1, refine_converged=True, warnings=("w",), candidates={"box": 0.875},
               input=path, component=component)


def test_a_fit_and_a_failure_become_the_infer_record_only_when_written():
    fit = outcome("b.png", component=1)
    assert to_record(fit) == {"input": "b.png", "shape": "box", "confidence": 0.875,
                              "keypoints": [[2.0 * i, 2.0 * i + 1] for i in range(8)],
                              "ratios": {"depth_height": 0.5, "width_height": 1.0}, "refine_steps": 1,
                              "refine_converged": True, "error": None, "warnings": ["w"], "candidates": {"box": 0.875}}
    assert to_record(fit, with_component=True)["component"] == 1
    failed = {"input": "a.png", "shape": None, "confidence": None, "keypoints": None, "ratios": None,
              "refine_steps": None, "refine_converged": None, "error": "cannot read", "warnings": [], "candidates": {}}
    assert to_record(outcome("a.png", None)) == failed
    both = to_record(outcome("a.png", None), with_component=True, cuboid=True)
    keys = [*failed]
    keys.insert(keys.index("ratios") + 1, "ratios_sd")  # the cuboid fit's error bars, beside the ratios
    assert list(both) == [*keys, "trust", "cuboid", "shape_call", "component"]
    assert both == failed | {"ratios_sd": None, "trust": None, "cuboid": None, "shape_call": None, "component": None}


def test_records_round_trip_with_their_index_and_input(tmp_path):
    out = tmp_path / "out.jsonl"
    with RecordStore(out) as store:
        store.write(1, [outcome("b.png")])
        store.write(0, [outcome("a.png", None)])
    assert read_records(out) == [{"index": 0} | to_record(outcome("a.png", None)),
                                 {"index": 1} | to_record(outcome("b.png"))]
    assert out.read_text().count("\n") == 2
    with RecordStore(out) as store:
        assert store.done == {"a.png", "b.png"} and len(store.records) == 2


def test_a_torn_last_line_is_ignored_then_cut_off_with_its_input_s_other_components(tmp_path):
    out = tmp_path / "out.jsonl"
    with RecordStore(out, COMPONENTS) as store:
        store.write(0, [outcome("a.png", component=0)])
        store.write(1, [outcome("b.png", component=0), outcome("b.png", component=1)])
    whole = out.read_bytes()
    out.write_bytes(whole[: whole.rindex(b"\n", 0, len(whole) - 1) + 20])  # b's second line, torn
    assert [r["input"] for r in read_records(out)] == ["a.png"]  # b is in OUT wholly or not at all
    with RecordStore(out, COMPONENTS) as store:
        assert store.done == {"a.png"}
        store.write(1, [outcome("b.png", component=0), outcome("b.png", component=1)])
    assert out.read_bytes() == whole


def test_a_file_that_is_not_an_infer_store_is_refused(tmp_path):
    out = tmp_path / "notes.jsonl"
    out.write_text('{"index": 0, "input": "a.png"}\nsome notes\n{"index": 1, "input": "b.png"}\n')
    with pytest.raises(UsageError, match="line 2 is not an infer record"):
        RecordStore(out).__enter__()


def test_a_full_disk_keeps_every_whole_record_and_says_so_in_one_line(tmp_path, monkeypatch):
    out = tmp_path / "out.jsonl"
    real_write, calls = os.write, []

    def write_then_fill(fd, data):
        calls.append(len(data))
        if len(calls) == 2:  # half of the second input's bytes, then the disk is full
            return real_write(fd, bytes(data[: len(data) // 2]))
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(store_module.os, "write", write_then_fill)
    with pytest.raises(UsageError, match="disk full after 1 records") as caught:
        with RecordStore(out) as store:
            store.write(0, [outcome("a.png")])
            store.write(1, [outcome("b.png")])
    assert "\n" not in str(caught.value)
    monkeypatch.undo()
    assert [r["input"] for r in read_records(out)] == ["a.png"] and out.read_text().endswith("\n")


def test_an_out_that_cannot_be_opened_or_synced_is_one_line_naming_it(tmp_path, monkeypatch):
    out = tmp_path / "out.jsonl"

    def read_only(*args):
        raise OSError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(store_module.os, "open", read_only)  # a file of another user, as that user sees it
    with pytest.raises(UsageError) as caught:
        RecordStore(out).__enter__()
    assert str(caught.value) == (f"--jsonl {out}: cannot open it to write (Permission denied); "
                                 f"expected a file this user can read and write")
    monkeypatch.undo()

    def io_error(fd):
        raise OSError(errno.EIO, "Input/output error")

    with pytest.raises(UsageError, match=r"cannot write after 1 records \(Input/output error; the whole ones on disk"):
        with RecordStore(out) as store:
            store.write(0, [outcome("a.png")])
            monkeypatch.setattr(store_module.os, "fsync", io_error)
    assert store.fd == -1  # closed all the same
