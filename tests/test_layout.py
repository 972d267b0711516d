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


def test_the_generator_never_imports_the_trainer():
    """The daemons meet only through the spool (docs/contract.md): the generator runs without torch's trainer."""
    generator = list((ROOT / "cuboidgen").rglob("*.py"))
    assert len(generator) > 10  # the scan sees the package
    offenders = {str(p.relative_to(ROOT)): sorted(m for m in imported_modules(p) if m.split(".")[0] == "cuboidtrain")
                 for p in generator}
    assert {p: m for p, m in offenders.items() if m} == {}


def test_shared_imports_neither_daemon():
    for path in (ROOT / "shared").rglob("*.py"):
        assert not {m.split(".")[0] for m in imported_modules(path)} & {"cuboidgen", "cuboidtrain"}, path


# ---- the import graph ------------------------------------------------------------------

PACKAGES = ("cuboidtrain", "shared", "cuboidgen")


def module_files() -> dict[str, Path]:
    """Every module of PACKAGES by its dotted name (a package by its `__init__.py`)."""
    modules = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def import_edges(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of `modules` that module `name` imports, at its top or inside a function.

    `from X import Y` is an import of the submodule X.Y where there is one, else of X;
    `import X.Y` is an import of X.Y (the packages above it only run their `__init__`)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: up level - 1 packages from this module's own
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        found.update(t for t in targets if t in modules and t != name)
    return found


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan), each
    as a path a -> b -> ... -> a, so a failure names the imports to cut."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph[node]):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(component)

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return [_cycle_through(min(component), component, graph) for component in components]


def _cycle_through(start: str, component: set[str], graph: dict[str, set[str]]) -> list[str]:
    """The shortest import path from `start` back to itself inside `component` (breadth first)."""
    came_from, frontier = {start: None}, [start]
    while frontier:
        following = []
        for node in frontier:
            for nxt in sorted(graph[node] & component):
                if nxt == start:
                    path = [node]
                    while came_from[path[-1]] is not None:
                        path.append(came_from[path[-1]])
                    return [start, *reversed(path[:-1]), start] if node != start else [start, start]
                if nxt not in came_from:
                    came_from[nxt] = node
                    following.append(nxt)
        frontier = following
    raise AssertionError(f"no cycle through {start}")


def test_import_graph_sees_submodules_and_function_level_imports():
    modules = module_files()
    assert {"cuboidtrain.fit.fitter", "shared.sample", "cuboidgen.daemon", "cuboidtrain"} <= set(modules)
    # `from cuboidtrain.fit.options import ...` at the top, and the zoo imported inside a method
    fitter = import_edges("cuboidtrain.fit.fitter", modules["cuboidtrain.fit.fitter"], modules)
    assert {"cuboidtrain.fit.options", "cuboidtrain.models.zoo"} <= fitter
    # `from cuboidtrain.models import compact`: the submodule, not the package
    assert "cuboidtrain.models.compact" in import_edges(
        "cuboidtrain.models.networks", modules["cuboidtrain.models.networks"], modules)
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    """A cycle works only while every module in it is imported in a lucky order; one moved
    import turns it into an ImportError for half-initialised modules."""
    modules = module_files()
    graph = {name: import_edges(name, path, modules) for name, path in modules.items()}
    assert [" -> ".join(cycle) for cycle in import_cycles(graph)] == []


# ---- the floors: each layer imports only the ones beneath it --------------------------

# cuboidtrain's layers, lowest first: the solver knows no network, the networks know no fit, the
# fit path knows neither the data floor nor the runners and the trainer; the experiments stand on
# all of them, the page (`serve`) on the experiments (its generated masks), and the command line on
# everything. Each may import any lower floor (and shared).
# A package's own `__init__` (the root `cuboidtrain`) is its name alone: the key matches no submodule.
FLOORS = {"cuboidtrain": 0, "cuboidtrain.allocator": 0, "cuboidtrain.geometry": 1, "cuboidtrain.models": 2,
          "cuboidtrain.fit": 3, "cuboidtrain.data": 4, "cuboidtrain.localize": 4, "cuboidtrain.infer": 5,
          "cuboidtrain.train": 5, "cuboidtrain.experiments": 6, "cuboidtrain.campaign": 6, "cuboidtrain.web": 7,
          "cuboidtrain.cli": 8, "cuboidtrain.__main__": 9}


def floor(module: str) -> tuple[str, int] | None:
    """The layer a module belongs to and its height; None for a module of no floor (of another package)."""
    for package, height in FLOORS.items():
        if module == package or (package not in PACKAGES and module.startswith(package + ".")):
            return package, height
    return None


def test_every_module_of_the_trainer_stands_on_a_floor():
    unplaced = sorted(name for name in module_files() if name.split(".")[0] == "cuboidtrain" and floor(name) is None)
    assert unplaced == []
    assert floor("cuboidtrain") == ("cuboidtrain", 0) and floor("cuboidtrain.nothing_here") is None


def climbs(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a module from a floor as high as its own or higher, but its own floor."""
    found = []
    for name, targets in graph.items():
        here = floor(name)
        for target in targets:
            there = floor(target)
            if here and there and there[0] != here[0] and there[1] >= here[1]:
                found.append(f"{name} -> {target}")
    return sorted(found)


def test_climbs_sees_an_import_up_a_floor_and_allows_one_down():
    assert climbs({"cuboidtrain.models.zoo": {"cuboidtrain.fit.options"}}) == [
        "cuboidtrain.models.zoo -> cuboidtrain.fit.options"]
    assert climbs({"cuboidtrain.infer.pool": {"cuboidtrain.train.loop"}}) == [
        "cuboidtrain.infer.pool -> cuboidtrain.train.loop"]  # side by side is no way down either
    assert climbs({"cuboidtrain.data.loader": {"cuboidtrain.train.distributed"}}) == [
        "cuboidtrain.data.loader -> cuboidtrain.train.distributed"]  # the data floor stands below the trainer
    assert climbs({"cuboidtrain.fit.fitter": {"cuboidtrain.models.zoo", "cuboidtrain.geometry.lift",
                                              "cuboidtrain.fit.options"}}) == []
    assert climbs({"cuboidtrain.cli": {"cuboidtrain.train.loop"}}) == []  # the command line stands on all


def test_no_import_climbs_back_up_a_floor():
    """The solver below the networks below the fit below the runners and the trainer: an arrow up
    ties a lower room to everything above it (the models once imported the trainer's DataLoader)."""
    modules = module_files()
    graph = {name: import_edges(name, path, modules) for name, path in modules.items()}
    assert climbs(graph) == []


def test_importing_the_fitter_loads_neither_the_trainer_nor_the_runners(fresh_interpreter):
    assert fresh_interpreter["fitter_loads"] == []


def private_imports(path: Path) -> list[str]:
    """`from X import _name`: a name its module keeps to itself, reached from outside."""
    return [f"{node.module}.{alias.name}" for node in ast.walk(ast.parse(path.read_text(), str(path)))
            if isinstance(node, ast.ImportFrom) and node.module != "__future__"
            for alias in node.names if alias.name.startswith("_") and not alias.name.startswith("__")]


def test_no_module_imports_a_private_name_of_another(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from a.b import _hidden, shown\nfrom __future__ import annotations\n")
    assert private_imports(probe) == ["a.b._hidden"]
    files = [p for folder in (*PACKAGES, "tests", "benchmarks") for p in (ROOT / folder).rglob("*.py")]
    found = {str(p.relative_to(ROOT)): private_imports(p) for p in files}
    assert {p: names for p, names in found.items() if names} == {}


def test_every_room_holds_at_most_twelve_modules_each_saying_its_role():
    rooms: dict[str, list[Path]] = {}
    for package in (*PACKAGES, "benchmarks"):
        for path in (ROOT / package).rglob("*.py"):
            rooms.setdefault(str(path.parent.relative_to(ROOT)), []).append(path)
    assert {"cuboidtrain/geometry", "cuboidtrain/fit", "cuboidtrain/data", "cuboidtrain/infer", "cuboidtrain/models",
            "benchmarks/accuracy", "benchmarks/calibration", "benchmarks/speed", "benchmarks/soak", "benchmarks/gpu"} <= set(rooms)
    assert {room: len(paths) for room, paths in rooms.items()
            if len([p for p in paths if p.name != "__init__.py"]) > 12} == {}
    silent = [str(p.relative_to(ROOT)) for paths in rooms.values() for p in paths
              if not (ast.get_docstring(ast.parse(p.read_text())) or "").strip()]
    assert silent == []


def test_no_module_name_means_two_things():
    """A module's name says its role once: the same file name in two folders of the packages is two
    meanings for one word (`files`, `camera`, `stopping` were). A package's `__init__`, `cli` (each
    daemon's command line) and `config` (each daemon's settings) are the one role in each."""
    roles = ("__init__.py", "__main__.py", "cli.py", "config.py", "dashboard.py")
    seen: dict[str, list[str]] = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            if path.name not in roles:
                seen.setdefault(path.name, []).append(str(path.relative_to(ROOT)))
    assert {name: paths for name, paths in seen.items() if len(paths) > 1} == {}


def readme_python_example() -> str:
    """The README's first ```python block in its "Python API" section."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


# Modules a fit with the shipped models does not need, each seconds to import on a small CPU:
# torchvision (only the `paper` arch's ResNet-18) pulls in torch._dynamo; matplotlib draws
# explanations only when asked; Dask (the optional cluster extra) only for `infer --cluster`.
# A one-mask `cuboidtrain infer` is mostly imports.
SLOW_IMPORTS = ("torchvision", "torch._dynamo", "matplotlib", "dask", "distributed")


@pytest.fixture(scope="module")
def fresh_interpreter() -> dict:
    """In a fresh interpreter at the repository's root (torch and the shipped models load once):
    which trainer and runner modules importing the fitter alone loaded, the README's example as
    written, then the same mask fitted from an array, and which cuboidgen modules and SLOW_IMPORTS
    all of that loaded."""
    example = readme_python_example()
    # One torch thread, as this process has (conftest): the same sums in the same order, the same floats.
    code = ("import sys, cuboidtrain.fit.fitter\nFITTER_LOADS = sorted(m for m in sys.modules if m.startswith("
            "('cuboidtrain.train', 'cuboidtrain.infer')))\n"
            f"SLOW_IMPORTS = {SLOW_IMPORTS!r}\nimport torch\ntorch.set_num_threads(1)\n" + example + "\nimport json, sys, cv2\nimport cuboidtrain.cli, cuboidtrain.fit.candidates\n"
            "from cuboidtrain import FitOptions\n"
            "fitter = Fitter.from_shipped(FitOptions(device='cpu', cuboid=True))\n"
            "array = fitter.fit(cv2.imread('examples/building.png', cv2.IMREAD_UNCHANGED))\n"
            "print(json.dumps({'fitter_loads': FITTER_LOADS, 'example': fit.record(), 'array': array.record(), 'generator': "
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
    assert "Fitter.from_shipped(FitOptions(cuboid=True))" in fresh_interpreter["code"] and ".fit(" in fresh_interpreter["code"]
    record = fresh_interpreter["example"]
    assert record["shape"] == "box" and len(record["keypoints"]) == 8 and record["error"] is None
    assert 0.5 < record["confidence"] <= 1


def test_the_api_fits_an_array_as_the_command_fits_its_file(fresh_interpreter):
    result = CliRunner().invoke(app, ["infer", "examples/building.png", "--device", "cpu"], catch_exceptions=False)
    assert result.exit_code == 0
    [by_command] = json.loads(result.stdout)
    assert by_command == fresh_interpreter["example"]  # the command, the API on a file, on an array: one path
    assert fresh_interpreter["array"] == by_command | {"input": None}
