"""Pipes end quietly (issue 30, Must have 3): a reader that closes stdout (`| head`) ends every command
that prints silently, exit 0 or 141 (128 + SIGPIPE), as Unix tools end.

Each command runs as a user runs it, its stdout a pipe whose reader is already gone (the
deterministic form of `| head -c 300`: every write fails at once).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import fill_spool

ROOT = Path(__file__).resolve().parents[1]


def run_into_closed_pipe(program: str, *args: str, stderr_too: bool = False) -> tuple[int, str]:
    """`program args` with stdout (and with `stderr_too` stderr) a pipe nobody reads: exit status, stderr."""
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run([sys.executable, "-c", f"from {program}.cli import main; main()", *args], cwd=ROOT,
                              stdout=write, stderr=write if stderr_too else subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(write)
    return done.returncode, done.stderr or ""


@pytest.fixture(scope="module")
def spool(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("spool")
    fill_spool(folder, 3)
    return folder


@pytest.mark.parametrize("program, args", [
    ("cuboidtrain", ["infer", "examples/building.png", "--json", "-", "--networks-only", "--device", "cpu"]),
    ("cuboidtrain", ["models", "--json"]),
    ("cuboidtrain", ["version"]),
    ("cuboidtrain", ["--help"]),
    ("cuboidtrain", ["infer", "--help"]),
    ("cuboidgen", ["scenes", "paper"]),
    ("cuboidgen", ["scenes"]),
    ("cuboidgen", ["inspect", "{spool}"]),
    ("cuboidgen", ["inspect", "{spool}", "--json"]),
    ("cuboidgen", ["run", "--help"]),
])
def test_a_closed_stdout_ends_a_command_quietly(program, args, spool):
    code, stderr = run_into_closed_pipe(program, *[a.format(spool=spool) for a in args])
    # infer's answer line and total go to stderr as the fit completes, before the JSON meets the closed pipe
    said = [line for line in stderr.splitlines() if not line.startswith(("examples/building.png  ", "1 mask; "))]
    assert code in (0, 141) and said == [], stderr


def test_a_closed_pipe_for_both_streams_is_quiet_too():
    code, _ = run_into_closed_pipe("cuboidtrain", "infer", "examples/building.png", "--networks-only", "--device", "cpu",
                                   stderr_too=True)
    assert code in (0, 141)


def test_another_broken_pipe_is_still_an_error(monkeypatch):
    """A BrokenPipeError that is not our reader's (a socket, a child's pipe) stays a one-line error."""
    import typer
    from typer.testing import CliRunner

    from shared.console import Commands

    app = typer.Typer(cls=Commands)

    @app.command()
    def talk() -> None:
        raise BrokenPipeError(32, "Broken pipe")

    @app.command()
    def other() -> None:
        pass

    result = CliRunner().invoke(app, ["talk"])
    assert result.exit_code == 2 and result.output == "error: [Errno 32] Broken pipe\n"
