"""`cuboidtrain.infer.run.infer`, the library call behind `cuboidtrain infer`: called directly it writes
the command's records, byte for byte, to a file or stdout; what the fitting gives back, in this
process or across a pool's process boundary, is typed (Fit, FitFailure) and carries no
explanation arrays; a fit whose numbers are not finite is a FitFailure saying which."""
from __future__ import annotations

import json
import logging
import os
import re

import cv2
import numpy as np

import pytest
from rich.console import Console
from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.fit.candidates import Scores
from cuboidtrain.fit.fitter import Fit, FitFailure, Fitter
from cuboidtrain.fit.options import FitOptions
from cuboidtrain.infer.batch import Batch, run_batch
from cuboidtrain.infer.run import InferRequest, infer
from cuboidtrain.models.zoo import default_checkpoints
from tests.conftest import write_mask_pngs

INFER = FitOptions(device="cpu", cuboid=True)  # what the command fits with its defaults


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> list[str]:
    """Three generated masks (box and twobox) and a file that is no image, last."""
    folder = tmp_path_factory.mktemp("masks")
    bad = folder / "x-bad.png"
    bad.write_text("not a picture")
    return write_mask_pngs(folder, 3) + [str(bad)]


def quiet() -> Console:
    return Console(file=open(os.devnull, "w"))


def test_the_library_call_writes_the_command_s_records_byte_for_byte(tmp_path, masks):
    command = CliRunner().invoke(app, ["infer", *masks, "--device", "cpu", "--json", str(tmp_path / "command.json")])
    assert command.exit_code == 1, command.output  # the file that is no image
    result = infer(InferRequest(paths=tuple(masks), options=INFER, json_out=str(tmp_path / "library.json")), quiet())
    assert (tmp_path / "library.json").read_bytes() == (tmp_path / "command.json").read_bytes()
    records = json.loads((tmp_path / "command.json").read_text())
    assert [r["input"] for r in records] == masks and [r["shape"] is None for r in records] == [False] * 3 + [True]
    assert all("cuboid" in r for r in records) and records[3]["error"]
    assert [type(o) for o in result.outcomes] == [Fit] * 3 + [FitFailure]
    assert (result.tally.total, result.tally.failed, result.pictures, result.meshes) == (4, 1, None, None)


def test_the_library_call_prints_the_command_s_list_to_stdout(masks, capsys):
    command = CliRunner().invoke(app, ["infer", *masks[:2], "--device", "cpu", "--networks-only"])
    assert command.exit_code == 0, command.output
    infer(InferRequest(paths=tuple(masks[:2]), options=FitOptions(device="cpu"), json_out="-"), quiet())
    printed = capsys.readouterr().out
    assert printed == command.stdout and len(json.loads(printed)) == 2


@pytest.mark.parametrize("workers", [1, 2])
def test_what_the_fitting_gives_back_is_typed_and_light_in_process_and_from_a_pool(masks, workers):
    options = FitOptions(device="cpu")
    checkpoints = default_checkpoints(None, options.shapes)
    batch = Batch(tuple(masks), tuple(checkpoints), options, workers)
    outcomes, tally = run_batch(batch, Fitter.from_files(checkpoints, options), quiet())
    assert [type(o) for o in outcomes] == [Fit] * 3 + [FitFailure]
    assert [o.input for o in outcomes] == masks
    assert all(o.explanation is None and o.keypoints.shape[1] == 2 for o in outcomes[:3])  # no arrays crossed
    assert masks[3] in outcomes[3].reason and "\n" not in outcomes[3].reason
    assert (tally.done, tally.failed, tally.shapes["failed"], sum(tally.shapes.values())) == (4, 1, 1, 4)


@pytest.mark.parametrize("workers", [1, 2])
def test_each_input_s_warnings_reach_this_process_s_log_once_in_process_and_from_a_pool(masks, tmp_path, workers,
                                                                                       caplog):
    cut = np.zeros((60, 90), np.uint8)
    cut[20:60, 0:30] = 255  # cut by the bottom and left border: a warning
    cv2.imwrite(str(tmp_path / "cut.png"), cut)
    inputs = (str(tmp_path / "cut.png"), masks[3])  # and the file that is no image: a failure
    options = FitOptions(device="cpu")
    checkpoints = default_checkpoints(None, options.shapes)
    with caplog.at_level(logging.WARNING):
        outcomes, _ = run_batch(Batch(inputs, tuple(checkpoints), options, workers),
                                Fitter.from_files(checkpoints, options), quiet())
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    expected = [f"{inputs[0]}: {w}" for w in outcomes[0].warnings] + [outcomes[1].reason]
    assert any("border" in w for w in outcomes[0].warnings)
    assert sorted(said) == sorted(expected)


def test_the_summary_s_counts_add_up_when_an_input_fails(masks, tmp_path):
    command = CliRunner().invoke(app, ["infer", str(tmp_path / "nothere.png"), masks[0], "--device", "cpu",
                                       "--json", str(tmp_path / "out.json")])
    assert command.exit_code == 1, command.output
    [summary] = [line for line in command.output.splitlines() if " masks; fitted " in line]
    found = re.search(r"^(\d+) masks; fitted (\d+) in .*; (\d+) failed(;|$)", summary)
    assert found, summary
    total, fitted, failed = map(int, found.groups()[:3])
    assert (total, fitted, failed) == (2, 1, 1)


def test_a_fit_whose_numbers_are_not_finite_is_a_failure_naming_the_field(masks, monkeypatch):
    monkeypatch.setattr("cuboidtrain.fit.fitter.assess", lambda *args: Scores(float("nan"), ()))
    fitter = Fitter.from_shipped(FitOptions(device="cpu", shape="box"))
    [failure] = fitter.outcomes(masks[:1])
    assert failure == FitFailure(masks[0], f"{masks[0]}: the fit's confidence is nan: no fit")
