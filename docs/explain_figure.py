"""Draw docs/explain-building.png, the README's panel, and print the line `infer` prints for it.

The panel is not drawn apart: this runs `cuboidtrain infer examples/building.png --explain DIR`
(`cuboidtrain.infer.run.infer`, the command's own call, with its default options), copies
DIR/building.png here and prints the answer line the command printed, which the README's caption
quotes (`tests/test_explain.py` fails when the caption and this line differ).

    .venv/bin/python docs/explain_figure.py [--out docs/explain-building.png]
"""
from __future__ import annotations

import argparse
import io
import os
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the checkout's packages, not an installed copy

from rich.console import Console  # noqa: E402

from cuboidtrain.fit.options import FitOptions  # noqa: E402
from cuboidtrain.infer.run import InferRequest, infer  # noqa: E402

INPUT = "examples/building.png"  # as the README's command names it, from the checkout's root


def answer_line(explain: Path | None = None) -> str:
    """The line `cuboidtrain infer examples/building.png` prints for the mask (run from the checkout's
    root), its panel written into `explain` when given."""
    console = Console(file=io.StringIO(), width=300)  # no terminal: plain text, no bar
    request = InferRequest(paths=(INPUT,), options=FitOptions(cuboid=True), explain=explain)
    infer(request, console)
    return console.file.getvalue().splitlines()[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "explain-building.png")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        line = answer_line(Path(folder))
        shutil.copyfile(Path(folder) / "building.png", args.out)
    print(line)


if __name__ == "__main__":
    os.chdir(ROOT)  # the input is named as the README's command names it
    main()
