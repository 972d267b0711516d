"""Both command lines' `--help` (issue 38): flags show no `<bool>`, arguments read as usual in the
usage line, and `infer --help` fits a 100-column terminal in groups."""
from __future__ import annotations

import re

import pytest
import typer.main
from rich.cells import cell_len
from typer.testing import CliRunner

from cuboidgen.cli import app as gen_app
from cuboidtrain.cli import INPUTS, CAMERA, MODELS, OUTPUT, SPEED, app as train_app

COLUMNS = 100


def command_paths(app) -> list[tuple]:
    """Every command and group of a command line, as the words that name it (the root: ())."""
    def walk(command, words):
        yield words
        for name, sub in getattr(command, "commands", {}).items():
            yield from walk(sub, words + (name,))
    return list(walk(typer.main.get_command(app), ()))


def help_text(app, words) -> str:
    result = CliRunner().invoke(app, [*words, "--help"], env={"COLUMNS": str(COLUMNS), "TERMINAL_WIDTH": None})
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.parametrize("app, words", [(app, words) for app in (gen_app, train_app) for words in command_paths(app)])
def test_no_flag_shows_a_bool_metavar_and_arguments_read_as_usual(app, words):
    text = help_text(app, words)
    assert "<bool>" not in text
    [usage] = [line for line in text.splitlines() if "Usage:" in line]
    assert "{" not in usage and "}" not in usage, usage


def test_the_masks_usage_names_its_arguments_plainly():
    usage = re.search(r"Usage: .*", help_text(gen_app, ("masks",))).group(0).rstrip()
    assert usage.endswith("masks [OPTIONS] SPOOL OUT_DIR")


def test_infer_s_help_fits_100_columns_in_groups():
    text = help_text(train_app, ("infer",))
    lines = text.splitlines()
    assert max(cell_len(line) for line in lines) <= COLUMNS
    titles = [re.search(r"╭─ (.*?) ─", line).group(1) for line in lines if line.startswith("╭─")]
    assert titles == ["Arguments", "Options", INPUTS, MODELS, CAMERA, OUTPUT, SPEED]
    assert len(lines) <= 120  # 166 in one panel whose help column was 28 wide
    for option in ("--camera", "--principal-px", "--focal-px"):  # each in its group
        camera = text.index(CAMERA)
        assert camera < text.index(f"│ {option} ") < text.index(OUTPUT)
