"""The walls between the parts, and the README's Python example run as written.

Inference must not depend on the generator: a change to a scene would otherwise
silently change what a shipped model infers. Only `cuboidtrain.experiments`
(which reproduces the paper by drawing samples) may import `cuboidgen`.
"""
from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    """Every module a file imports, at its top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_only_the_experiments_import_the_generator():
    library = [p for p in (ROOT / "cuboidtrain").rglob("*.py") if "experiments" not in p.relative_to(ROOT).parts]
    assert len(library) > 20  # the scan sees the package
    offenders = {str(p.relative_to(ROOT)): sorted(m for m in imported_modules(p) if m.split(".")[0] == "cuboidgen")
                 for p in library}
    assert {p: m for p, m in offenders.items() if m} == {}


def test_shared_imports_neither_daemon():
    for path in (ROOT / "shared").rglob("*.py"):
        assert not {m.split(".")[0] for m in imported_modules(path)} & {"cuboidgen", "cuboidtrain"}, path


def readme_python_example() -> str:
    """The README's first ```python block in its "Python API" section."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


# Modules a fit with the shipped models does not need, each seconds to import on a small CPU:
# torchvision (only the `paper` arch's ResNet-18) pulls in torch._dynamo; matplotlib draws
# explanations only when asked. A one-mask `cuboidtrain infer` is mostly imports.
SLOW_IMPORTS = ("torchvision", "torch._dynamo", "matplotlib")


@pytest.fixture(scope="module")
def fresh_interpreter() -> dict:
    """In a fresh interpreter at the repository's root (torch and the shipped models load once):
    the README's example as written, then the same mask fitted from an array, and which
    cuboidgen modules and SLOW_IMPORTS all of that loaded."""
    example = readme_python_example()
    # One torch thread, as this process has (conftest): the same sums in the same order, the same floats.
    code = (f"SLOW_IMPORTS = {SLOW_IMPORTS!r}\nimport torch\ntorch.set_num_threads(1)\n" + example + "\nimport json, sys, cv2\nimport cuboidtrain.cli, cuboidtrain.fit.chain\n"
            "from cuboidtrain import FitOptions\n"
            "fitter = Fitter.from_shipped(FitOptions(device='cpu'))\n"
            "array = fitter.fit(cv2.imread('examples/building.png', cv2.IMREAD_UNCHANGED))\n"
            "print(json.dumps({'example': fit.record(), 'array': array.record(), 'generator': "
            "sorted(m for m in sys.modules if m.split('.')[0] == 'cuboidgen'), "
            "'slow_imports': sorted(m for m in SLOW_IMPORTS if m in sys.modules)}))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return {"code": example} | json.loads(done.stdout.strip().splitlines()[-1])


def test_fitting_a_mask_never_loads_the_generator(fresh_interpreter):
    assert fresh_interpreter["generator"] == []


def test_fitting_a_mask_imports_nothing_slow_it_does_not_need(fresh_interpreter):
    assert fresh_interpreter["slow_imports"] == []


def test_the_readme_python_example_runs_as_written(fresh_interpreter):
    assert "Fitter.from_shipped()" in fresh_interpreter["code"] and ".fit(" in fresh_interpreter["code"]
    record = fresh_interpreter["example"]
    assert record["shape"] == "box" and len(record["keypoints"]) == 8 and record["error"] is None
    assert 0.5 < record["confidence"] <= 1


def test_the_api_fits_an_array_as_the_command_fits_its_file(fresh_interpreter):
    result = CliRunner().invoke(app, ["infer", "examples/building.png", "--device", "cpu"], catch_exceptions=False)
    assert result.exit_code == 0
    [by_command] = json.loads(result.stdout)
    assert by_command == fresh_interpreter["example"]  # the command, the API on a file, on an array: one path
    assert fresh_interpreter["array"] == by_command | {"input": None}
