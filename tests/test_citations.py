"""What the documents cite exists (issue 36, Must have 5): every file path, test name, module name
and benchmark command in README.md, docs/**/*.md, BENCHMARKS.md and RELIABILITY.md.

Read without importing the project (no torch): test names are the `def test_*` of tests/ (ast); a
dotted name such as `cuboidtrain.fit.masks.silhouette` or `geometry.lift.lift` must name a module
and a name it defines; a benchmark's options are those its argparse parser declares (ast), checked
against the script's own `--help` for the scripts that start without torch.
"""
from __future__ import annotations

import ast
import fnmatch
import functools
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.pages import ROOT, commands, shell_lines

PAGES = sorted([ROOT / "README.md", ROOT / "BENCHMARKS.md", ROOT / "RELIABILITY.md", *(ROOT / "docs").rglob("*.md")])
PACKAGES = ("cuboidtrain", "cuboidgen")  # a short path or dotted name (`fit/masks.py`, `fit.masks`) is under one
SOURCE_ROOTS = {"cuboidtrain", "cuboidgen", "shared", "tests", "benchmarks", "docs", "recipes", "ops", "examples",
                "reports", ".ci"}
TOP_FILES = {"Makefile", "Dockerfile", "docker-compose.yml", "constraints.txt", "pyproject.toml"}
FILE_TYPES = "py|sh|md|png|json|yml|yaml|txt|toml|csv"
# docs/research/ describes a prototype that lived in research/geometric_fit_prototype/ (commit 0ab788a) and
# is gone from the tree: its bare file names (measure_lift.py, test_model.py) are history, not citations
HISTORY = ("docs/research/",)

PATH = re.compile(rf"(?<![\w./~$*-])((?:\.\./)*[\w.*-]+(?:/[\w.*-]+)*\.(?:{FILE_TYPES}))(?![\w/-])")
TEST = re.compile(r"(?:(?<![\w/.])([\w/]*test_\w+\.py)::|(?<![\w/.*]))(test_\w+\*?)(?![\w.(])")
DOTTED = re.compile(r"`((?:cuboidtrain|cuboidgen|shared|geometry|models|fit|infer|train|data|experiments)"
                    r"(?:\.\w+)+)(?:\(\))?`")
MEMBER = re.compile(r"`([A-Z]\w+)\.(\w+)(?:\([^`]*\))?`")  # `Fitter.outcomes`, `Fitter.fit(...)`
SCRIPT = re.compile(r"(?<![\w/.-])((?:benchmarks/(?:\w+/)*)?(?:bench|soak|snapshot)_\w+\.py)((?:\s+[^`\n]*)?)")


@functools.cache
def repo_files() -> frozenset[str]:
    """Every tracked and untracked (not ignored) file, relative to the root."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    return frozenset(line for line in out.splitlines() if (ROOT / line).exists())


@functools.cache
def folders() -> frozenset[str]:
    return frozenset(str(parent) for f in repo_files() for parent in Path(f).parents if str(parent) != ".")


def path_exists(path: str, page_dir: Path) -> bool:
    """A cited path: from the root, from the page's folder, or under a package (`fit/masks.py`);
    a bare file name anywhere in the tree; a glob where one file matches."""
    if path.startswith("../"):
        candidates = [str((page_dir / path).resolve().relative_to(ROOT))]
    elif "/" not in path:
        return any(fnmatch.fnmatch(Path(f).name, path) for f in repo_files())
    else:
        candidates = [path, str((page_dir / path).relative_to(ROOT)) if page_dir != ROOT else path,
                      *(f"{package}/{path}" for package in PACKAGES)]
    return any(fnmatch.filter(repo_files(), c) or c in folders() for c in candidates)


def is_source_path(path: str) -> bool:
    """Whether a path names a file of this tree (rather than an output: runs/, /tmp, report.json)."""
    first = path.split("/")[0]
    if path.startswith("../") or first in SOURCE_ROOTS or path in TOP_FILES:
        return True
    if "/" in path:
        return any((ROOT / package / first).is_dir() for package in PACKAGES)
    return path.endswith((".py", ".sh")) or bool(re.fullmatch(r"[A-Z]+\.md", path))


@functools.cache
def collected_tests() -> dict[str, frozenset[str]]:
    """The test functions of each tests/ file (methods of test classes included)."""
    names = {}
    for file in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(file.read_text())
        names[file.name] = frozenset(node.name for node in ast.walk(tree)
                                     if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                                     and node.name.startswith("test_"))
    return names


def cited_test_exists(name: str, file: str | None) -> bool:
    """A cited test: `test_foo`, a glob `test_foo_*`, or `tests/test_x.py::test_foo`; a module's name too."""
    files = collected_tests()
    if file is not None:
        return Path(file).name in files and bool(fnmatch.filter(files[Path(file).name], name))
    return any(fnmatch.filter(names, name) for names in files.values()) or f"{name}.py" in files


def assigned(body: list[ast.stmt]) -> set[str]:
    """The names a block of statements binds: functions, classes, assignments (tuples too)."""
    names = set()
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                elements = target.elts if isinstance(target, ast.Tuple) else [target]
                names |= {e.id for e in elements if isinstance(e, ast.Name)}
    return names


@functools.cache
def module_names(file: Path) -> dict[str, frozenset[str]]:
    """A module's top-level names, and each class's names under its own key."""
    tree = ast.parse(file.read_text())
    top, members = set(assigned(tree.body)), {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            top.add(node.name)
            if isinstance(node, ast.ClassDef):
                members[node.name] = frozenset(assigned(node.body))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            top |= {(a.asname or a.name).split(".")[0] for a in node.names}
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict) and "__getattr__" in top:
            top |= {k.value for k in node.value.keys if isinstance(k, ast.Constant)}  # names imported lazily
    return {"": frozenset(top), **members}


@functools.cache
def classes() -> dict[str, frozenset[str]]:
    """Every class of the packages and what its body defines (several classes of one name pooled)."""
    found: dict[str, set[str]] = {}
    for package in (*PACKAGES, "shared"):
        for file in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(file.read_text())):
                if isinstance(node, ast.ClassDef):
                    found.setdefault(node.name, set()).update(assigned(node.body))
    return {name: frozenset(members) for name, members in found.items()}


def member_exists(owner: str, name: str) -> bool:
    """`Fitter.outcomes`: the class, where this tree defines one of that name, has that member."""
    return owner not in classes() or name in classes()[owner]


def dotted_exists(name: str) -> bool:
    """`cuboidtrain.fit.masks.silhouette`, `fit.masks.silhouette`, `shared.camera`: a module (or
    package) and, after it, a name it defines, and a class's member after that."""
    parts = name.split(".")
    roots = [[]] if parts[0] in {"cuboidtrain", "cuboidgen", "shared"} else [[p] for p in PACKAGES]
    for root in roots:
        for k in range(len(parts), 0, -1):
            base = ROOT.joinpath(*root, *parts[:k])
            file = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
            if not file.is_file():
                continue
            rest = parts[k:]
            if not rest:
                return True
            names = module_names(file)
            if rest[0] not in names[""] and not (base.is_dir() and (base / rest[0]).exists()):
                return False
            return len(rest) == 1 or rest[0] not in names or rest[1] in names[rest[0]]
    return False


@functools.cache
def script_options(script: Path) -> frozenset[str]:
    """The long options a benchmark's argparse parser declares (`add_argument("--x", ...)`), and --help."""
    options = {"--help", "-h"}
    for node in ast.walk(ast.parse(script.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
            declared = {a.value for a in node.args if isinstance(a, ast.Constant) and str(a.value).startswith("-")}
            if any(getattr(k.value, "attr", None) == "BooleanOptionalAction" for k in node.keywords):
                declared |= {f"--no-{d[2:]}" for d in declared if d.startswith("--")}
            options |= declared
    return frozenset(options)


def find_script(cited: str) -> Path | None:
    """A cited benchmark: its path, or its bare name wherever it lies under benchmarks/."""
    if "/" in cited:
        return ROOT / cited if (ROOT / cited).is_file() else None
    found = sorted((ROOT / "benchmarks").rglob(cited))
    return found[0] if found else None


def script_calls(text: str) -> list[tuple[str, list[str]]]:
    """Every (script, options) of a benchmark's command: in ```bash blocks, and in inline code."""
    calls = []
    for line in shell_lines(text):
        if not SCRIPT.search(line):
            continue
        try:
            split = commands(line)
        except ValueError:  # a quote closed on a later line (python -c "..."): plain words will do
            split = [line.split()]
        for command in split:
            for k, word in enumerate(command):
                if SCRIPT.fullmatch(word):
                    calls.append((word, [w for w in command[k + 1:] if w.startswith("-")]))
                    break
    for span in re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S)):
        for match in SCRIPT.finditer(span):
            calls.append((match[1], re.findall(r"(?<![\w-])--?[a-zA-Z][\w-]*", match[2])))
    return calls


def problems(text: str, page_dir: Path = ROOT, history: bool = False) -> list[str]:
    """What a page cites that does not exist, one line each."""
    found = []
    for match in PATH.finditer(text):
        path = match[1]
        if is_source_path(path) and not (history and "/" not in path) and not path_exists(path, page_dir):
            found.append(f"no file {path}")
    for match in TEST.finditer(text):
        if not cited_test_exists(match[2], match[1]):
            found.append(f"no test {match[1] + '::' if match[1] else ''}{match[2]}")
    for match in DOTTED.finditer(text):
        if not dotted_exists(match[1]):
            found.append(f"no module or name {match[1]}")
    for match in MEMBER.finditer(text):
        if not member_exists(match[1], match[2]):
            found.append(f"no member {match[1]}.{match[2]}")
    for cited, options in script_calls(text):
        script = find_script(cited)
        if script is None:
            found.append(f"no benchmark {cited}")
            continue
        for option in options:
            if option.split("=")[0] not in script_options(script):
                found.append(f"{cited}: no option {option}")
    return sorted(set(found))


def page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=page_id)
def test_every_citation_exists(page):
    history = page_id(page).startswith(HISTORY)
    assert problems(page.read_text(), page.parent, history) == [], page_id(page)


def test_the_pages_cite_enough_to_check():
    text = "\n".join(page.read_text() for page in PAGES)
    assert len(set(PATH.findall(text))) > 100
    assert len(TEST.findall(text)) > 15
    assert len(script_calls(text)) > 20


SYNTHETIC = """
The fit is in `cuboidtrain/geometry/no_such_module.py` and `fit/nowhere.py`; see docs/no-page.md.
`tests/test_citations.py::test_nothing_by_this_name` and `test_no_such_prefix_*` hold it.
`cuboidtrain.fit.masks.no_such_function` and `geometry.no_module.lift` do the work, as `Fitter.no_such_method`.

```bash
python benchmarks/bench_no_such_script.py --samples 3
python {bench_cli} --repeats 5 --no-such-option
```

Inline: `bench_cli.py --repeats 5 --also-not-an-option`.
"""


def test_a_missing_citation_is_caught():
    bench_cli = str(find_script("bench_cli.py").relative_to(ROOT))
    assert problems(SYNTHETIC.replace("{bench_cli}", bench_cli)) == sorted([
        "no file cuboidtrain/geometry/no_such_module.py", "no file fit/nowhere.py", "no file docs/no-page.md",
        "no test tests/test_citations.py::test_nothing_by_this_name", "no test test_no_such_prefix_*",
        "no module or name cuboidtrain.fit.masks.no_such_function", "no module or name geometry.no_module.lift",
        "no member Fitter.no_such_method",
        "no benchmark benchmarks/bench_no_such_script.py", "no file benchmarks/bench_no_such_script.py",
        f"{bench_cli}: no option --no-such-option", "bench_cli.py: no option --also-not-an-option",
    ])


def test_what_exists_passes():
    text = """`cuboidtrain/fit/masks.py`, `fit/masks.py`, shared/sample.py, [the layout](docs/layout.md),
    `tests/test_citations.py::test_a_missing_citation_is_caught`, `test_a_missing_*`, test_citations,
    `cuboidtrain.fit.masks.silhouette`, `fit.masks.silhouette`, `shared.camera`, `runs/demo/infer.json`,
    `bench_cli.py --repeats 7 --json x.json`, `Fitter.fit`, `Fitter.from_shipped()`, `Fit.candidates`
    """
    assert problems(text) == []


@pytest.mark.parametrize("name", ["bench_cli.py", "bench_workers.py", "soak_kill.py"])
def test_the_declared_options_are_what_help_accepts(name):
    """The scripts that start without torch: their `--help` lists what the ast found, no more."""
    script = find_script(name)
    assert script is not None, name
    shown = subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT, capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60, check=True).stdout
    assert set(re.findall(r"(?<![\w-])--[a-z][\w-]*", shown)) | {"-h"} == set(script_options(script))


def test_the_measurement_pages_are_references_with_contents_not_logs():
    # issue 36: BENCHMARKS.md had grown to a 113 KB diary; today's figures only, each area findable
    for page, most in (("BENCHMARKS.md", 40_000), ("RELIABILITY.md", 40_000)):
        text = (ROOT / page).read_text(encoding="utf-8")
        assert len(text.encode()) <= most, f"{page}: {len(text.encode()):,} bytes, at most {most:,}"
        assert "\n## Contents\n" in text, f"{page}: no table of contents"
