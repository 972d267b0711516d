"""What the user got wrong, reported once: the UsageError type, output paths checked before any work,
the one place both command lines turn an error into one line, and `run`'s defaults read from TrainConfig.

The tests run as root, for whom every folder is writable: an unwritable place is a path under a
regular file, or a folder where a file is to be written.
"""
from dataclasses import fields
from enum import Enum
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from cuboidgen.cli import app as gen_app
from cuboidtrain.cli import app as train_app
from cuboidtrain.train.config import TrainConfig
from cuboidtrain.data.reframing import CutOff
from shared.console import Commands
from shared.errors import UsageError, check_outputs, check_writable
from shared.spool import SpoolError

runner = CliRunner()


def one_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    return lines[0]


@pytest.fixture
def a_file(tmp_path) -> Path:
    path = tmp_path / "a-file"
    path.write_text("not a folder")
    return path


# --- the type ------------------------------------------------------------------

def test_a_usage_error_is_a_value_error_and_a_skipped_sample_is_neither():
    assert issubclass(UsageError, ValueError) and issubclass(SpoolError, UsageError)
    assert not issubclass(CutOff, ValueError)  # control flow in the sampler, never a user's error


# --- output paths --------------------------------------------------------------

def test_a_folder_can_be_new_a_files_folder_must_exist_and_nothing_is_made_now(tmp_path):
    target = tmp_path / "x.json"
    assert check_writable("--json", target) == target
    assert check_writable("--out", tmp_path / "run", folder=True) == tmp_path / "run"
    assert check_writable("--out", tmp_path / "runs" / "p1", folder=True) == tmp_path / "runs" / "p1"
    assert check_writable("--out", tmp_path, folder=True) == tmp_path  # an existing folder: written into
    missing = tmp_path / "new" / "deeper" / "x.json"  # a typo in a folder is not made into folders
    with pytest.raises(UsageError, match=f"^--json {missing}: no folder {missing.parent} to write it in "
                                         f"\\(expected an existing folder\\)$"):
        check_writable("--json", missing)
    assert list(tmp_path.iterdir()) == []
    check_outputs(("--json", "-"), ("--bars", None))  # stdout and not asked for: nothing to check


@pytest.mark.parametrize("folder", [False, True])
def test_a_path_under_a_file_names_the_option_and_the_file(a_file, folder):
    with pytest.raises(UsageError, match=f"^--out {a_file}/x/y: {a_file} is not a folder$"):
        check_writable("--out", a_file / "x" / "y", folder=folder)


def test_a_folder_is_not_a_file_to_write_nor_a_file_a_folder(tmp_path, a_file):
    with pytest.raises(UsageError, match=f"^--json {tmp_path}: a folder, expected a file to write$"):
        check_outputs(("--json", tmp_path))
    with pytest.raises(UsageError, match=f"^--explain {a_file}: not a folder$"):
        check_writable("--explain", a_file, folder=True)


def test_a_folder_that_cannot_be_written_in_is_refused(tmp_path, monkeypatch):
    import os

    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != tmp_path)  # root may write anywhere
    with pytest.raises(UsageError, match=f"cannot write in {tmp_path} \\(permission denied\\)"):
        check_writable("--onnx", tmp_path / "m.onnx")


def test_infer_checks_json_and_explain_before_it_fits(tmp_path, a_file, monkeypatch):
    from cuboidtrain.fit.fitter import Fitter

    def no_fitting(*args, **kwargs):
        raise AssertionError("models loaded before the output paths were checked")

    import os

    monkeypatch.setattr(Fitter, "from_files", no_fitting)
    (locked := tmp_path / "locked").mkdir()
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != locked)  # root may write anywhere
    for option, path, message in (("--json", locked / "out.json", f"cannot write in {locked} (permission denied)"),
                                  ("--json", a_file / "out.json", f"{a_file} is not a folder"),
                                  ("--json", tmp_path, "a folder, expected a file to write"),
                                  ("--json", tmp_path / "nowhere" / "x.json",
                                   f"no folder {tmp_path / 'nowhere'} to write it in (expected an existing folder)"),
                                  ("--explain", a_file, "not a folder"),
                                  ("--explain", a_file / "pictures", f"{a_file} is not a folder")):
        result = runner.invoke(train_app, ["infer", "examples/building.png", option, str(path), "--device", "cpu"])
        assert result.exit_code == 2
        assert one_line(result) == f"error: {option} {path}: {message}"


def test_run_checks_out_before_it_trains(tmp_path, a_file, monkeypatch):
    import cuboidtrain.train.loop as loop

    def no_training(*args, **kwargs):
        raise AssertionError("training started before --out was checked")

    monkeypatch.setattr(loop, "run", no_training)
    for out, message in ((a_file, "not a folder"), (a_file / "run", f"{a_file} is not a folder")):
        result = runner.invoke(train_app, ["run", "--spool", str(tmp_path), "--out", str(out), "--steps", "1",
                                           "--no-dashboard", "--device", "cpu"])
        assert result.exit_code == 2
        assert one_line(result) == f"error: --out {out}: {message}"


@pytest.mark.parametrize("program, args", [
    ("cuboidtrain", ["export", "--onnx", "{bad}"]),
    ("cuboidtrain", ["localize", "--street", "street.json", "--json", "{bad}", "m.png"]),
    ("cuboidtrain", ["localize", "--street", "street.json", "--bars", "{bad}", "m.png"]),
    ("cuboidtrain", ["localize-experiment", "--oracle", "--csv", "{bad}"]),
    ("cuboidtrain", ["report", "--clean-spool", "spool", "--out", "{bad}"]),
    ("cuboidtrain", ["models", "pack", "--checkpoint", "last.pt", "--out", "{bad}"]),
    ("cuboidgen", ["preview", "spool", "--out", "{bad}"]),
    ("cuboidgen", ["occluders", "preview", "--out", "{bad}"]),
    ("cuboidgen", ["occluders", "extract", "--cityscapes", "cs", "--out", "{bad}"]),
    ("cuboidgen", ["bench", "--json", "{bad}"]),
])
def test_every_output_option_is_checked_first(program, args, a_file):
    bad = a_file / "x"
    result = runner.invoke({"cuboidtrain": train_app, "cuboidgen": gen_app}[program],
                           [str(bad) if a == "{bad}" else a for a in args])
    option = args[args.index("{bad}") - 1]
    assert result.exit_code == 2
    assert one_line(result) == f"error: {option} {bad}: {a_file} is not a folder"


# --- the one channel -------------------------------------------------------------

def toy_app() -> typer.Typer:
    app = typer.Typer(cls=Commands)

    @app.command()
    def usage():
        raise UsageError("--size 7: expected a multiple of 32")

    @app.command()
    def unreadable():
        open("/nonexistent/mask.png")

    @app.command()
    def bug():
        raise ValueError("a bug of ours")

    return app


def test_usage_and_path_errors_are_one_line_and_exit_2_anything_else_is_ours():
    app = toy_app()
    result = runner.invoke(app, ["usage"])
    assert result.exit_code == 2 and one_line(result) == "error: --size 7: expected a multiple of 32"
    result = runner.invoke(app, ["unreadable"])
    assert result.exit_code == 2
    assert one_line(result) == "error: [Errno 2] No such file or directory: '/nonexistent/mask.png'"
    result = runner.invoke(app, ["bug"])
    assert isinstance(result.exception, ValueError) and str(result.exception) == "a bug of ours"


# --- run's defaults ----------------------------------------------------------------

def test_every_run_option_defaults_to_its_train_config_field():
    run = typer.main.get_command(train_app).commands["run"]
    options = {p.name: p.default for p in run.params}
    defaults = {f.name: f.default for f in fields(TrainConfig)}
    assert set(options) == set(defaults)  # one option per field, one field per option

    def plain(value):
        return value.value if isinstance(value, Enum) else str(value) if isinstance(value, Path) else value

    # --out follows --phase (runs/p1, runs/p2, ...); TrainConfig's is phase 1's
    assert options.pop("out") is None and defaults.pop("out") == "runs/p1" and defaults["phase"] == "1"
    assert {name: plain(value) for name, value in options.items()} == defaults


def test_an_error_line_keeps_the_brackets_it_quotes(capsys):
    """A message quoting a list ([nan, 1.0]) is printed as written, not read as rich markup."""
    import typer

    from shared.console import fail

    with pytest.raises(typer.Exit):
        fail("scene 'x': width [nan, 1.0]: expected a range [min, max]")
    out = capsys.readouterr()
    assert "width [nan, 1.0]: expected a range [min, max]" in (out.err + out.out)
