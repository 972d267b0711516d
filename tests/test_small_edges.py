"""The small ones (issue 30, Must have 6): help text that shows what it says, a panel title whose choice
reads as one, a model table that splits no number, and a trainer dashboard that redraws in place.
"""
from __future__ import annotations

import logging
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import typer
from rich.console import Console
from rich.text import Text

from cuboidtrain.cli import app as train_app
from cuboidgen.cli import app as gen_app
from tests.conftest import command_here

ROOT = Path(__file__).resolve().parents[1]


def commands(app, name: str):
    """Every (path, click command) of a typer app, subcommands included."""
    def walk(command, path):
        yield path, command
        for sub_name, sub in getattr(command, "commands", {}).items():
            yield from walk(sub, path + [sub_name])

    yield from walk(typer.main.get_command(app), [name])


@pytest.mark.parametrize("app, name", [(train_app, "cuboidtrain"), (gen_app, "cuboidgen")])
def test_no_help_text_loses_words_to_rich_markup(app, name):
    """typer renders help as rich markup: `[cluster]` in `pip install 'cuboid-fit[cluster]'` was read as a
    style and dropped. Every command's and option's help shows all its text."""
    for path, command in commands(app, name):
        for text in [command.help or ""] + [getattr(p, "help", None) or "" for p in command.params]:
            shown = Text.from_markup(text).plain
            assert shown == text.replace("\\[", "["), (" ".join(path), text)


def test_infer_help_names_the_cluster_extra():
    done = subprocess.run([sys.executable, "-c", "from cuboidtrain.cli import main; main()", "infer", "--help"],
                          cwd=ROOT, capture_output=True, text=True, env={"COLUMNS": "300", "PATH": ""}, timeout=300)
    assert done.returncode == 0 and "pip install 'cuboid-fit[cluster]'" in done.stdout


def test_the_panel_title_says_why_a_lower_score_won_in_digits_that_tell_them_apart():
    """0.903 against 0.901 read "box, confidence 0.90 (vs twobox 0.90)": a choice that looked arbitrary,
    and nothing said why the lower one won (the richer shape's margin, or its fit set aside)."""
    import numpy as np

    from cuboidtrain.fit.fitter import Fit
    from cuboidtrain.infer.explain import choice_reason

    def reason(candidates: dict, cuboid=None, warnings=()) -> str | None:
        fit = Fit(shape="box", keypoints=np.zeros((8, 2)), ratios={"depth_height": 1.0, "width_height": 1.0},
                  confidence=candidates["box"], refine_steps=1, refine_converged=True, candidates=candidates,
                  input="m.png", cuboid=cuboid, warnings=warnings)
        return choice_reason(fit)

    assert reason({"box": 0.903, "twobox": 0.906}, cuboid="fitted") == \
        "box: twobox's IoU 0.906 is not 0.005 above the box's 0.903, the margin a richer shape must win by"
    assert reason({"box": 0.9031, "twobox": 0.9032}) == \
        "box: twobox's confidence 0.9032 is not 0.02 above the box's 0.9031, the margin a richer shape must win by"
    aside = ("the twobox cuboid explained the input better (IoU 0.950 against 0.903) but was set aside: its two "
             "parts' heights differ by 3% (< 10%): a box with a seam")
    assert reason({"box": 0.903, "twobox": 0.95}, cuboid="fitted", warnings=(aside,)) == \
        "box: twobox's IoU 0.950 is higher, but the twobox was set aside: its two parts' heights differ by 3% " \
        "(< 10%): a box with a seam"
    assert reason({"box": 0.93, "twobox": 0.41}) is None and reason({"box": 0.5}) is None  # it scored highest
    from cuboidtrain.fit.shape_call import CLASSIFIER, ShapeCall

    called = Fit(shape="box", keypoints=np.zeros((8, 2)), ratios={"depth_height": 1.0, "width_height": 1.0},
                 confidence=0.9, refine_steps=1, refine_converged=True, candidates={"box": 0.9, "twobox": 0.93},
                 cuboid="fitted", shape_call=ShapeCall(CLASSIFIER, 0.12))
    assert choice_reason(called) == "box: the shape classifier's call on this rough silhouette (88% sure); twobox's IoU 0.930 is higher than the box's 0.900"


def test_the_model_table_splits_no_number_in_80_columns_without_a_terminal():
    done = command_here(["models"], env={"COLUMNS": "80", "PATH": ""})
    assert done.returncode == 0
    rows = [line for line in done.stderr.splitlines() if line.startswith("│ ")]
    # one line a model, nothing wrapped: the box and twobox models and the shape classifier between them
    assert [row.split("│")[1].strip() for row in rows] == ["box", "box|twobox", "twobox"]
    assert [row.split("│")[4].strip() for row in rows] == ["grey"] * 3  # every shipped model reads grey inputs
    for row in rows:
        figures = r"-/-/-" if "classifier" in row else r"\d+\.\d\d/\d+\.\d\d/\d+\.\d\d"  # corner errors: the fitting models'
        assert re.search(rf"│ [\d,]+ +│ [\d,]+ +│ \d+\.\d\d +│ {figures} +│ \d+\.\d │$", row), row


# --- the trainer's dashboard redraws in place ----------------------------------------------

def screen(data: str) -> list[str]:
    """The lines a terminal shows (scrollback included) for `data`: text, \\r, \\n, and the cursor
    moves rich's Live uses (ESC[1A up, ESC[2K erase the line); other escapes are dropped."""
    lines, row, col = [""], 0, 0
    for token in re.findall(r"\x1b\[[0-9;?]*[A-Za-z]|\r|\n|[^\x1b\r\n]+", data):
        if token == "\n":
            row, col = row + 1, 0
            if row == len(lines):
                lines.append("")
        elif token == "\r":
            col = 0
        elif token == "\x1b[1A":
            row = max(row - 1, 0)
        elif token == "\x1b[2K":
            lines[row] = ""
        elif not token.startswith("\x1b"):
            line = lines[row].ljust(col)
            lines[row] = line[:col] + token + line[col + len(token):]
            col += len(token)
    return lines


def test_a_warning_logged_while_the_dashboard_is_live_leaves_no_stale_panel(monkeypatch):
    """The warning the trainer logs when samples are evicted unread (at an epoch's change) was written
    past rich's Live, on another console: each left the top of a panel behind (issue 30, finding 5)."""
    import io

    import shared.console
    from cuboidtrain.train.monitor import dashboard
    from tests.test_train_dashboard import status

    out = io.StringIO()
    terminal = Console(file=out, force_terminal=True, width=100, color_system=None)
    monkeypatch.setattr(shared.console, "console", terminal)  # what stderr is in a terminal
    monkeypatch.setattr(dashboard, "log_console", terminal)
    shared.console.setup_logging()  # the command's logging: a RichHandler on that console
    try:
        with dashboard.Dashboard(live=True) as board:  # the default console, as `cuboidtrain run` makes it
            for step in range(1, 6):
                board.update(replace(status(step=step), notes=[]))
                logging.getLogger("cuboidtrain.train.loop").warning("%d samples evicted before the trainer read "
                                                                    "them since the last warning", 100 * step)
    finally:
        logging.getLogger().handlers.clear()
    shown = screen(out.getvalue())
    assert sum("cuboidtrain" in line and "╭" in line for line in shown) == 1, "\n".join(shown)
    assert sum("samples evicted" in line for line in shown) == 5
    assert "step 5 / 1,000" in "\n".join(shown)
