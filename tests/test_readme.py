"""The README a newcomer reads (issue 30, Must have 4): at most 15 KB, and every command in its code blocks
and in docs/'s parses: each `cuboidgen` and `cuboidtrain` line is parsed by its subcommand as the
command line parses it (options, their values and choices), each `make` target is the Makefile's, and
each script it runs exists.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import typer

from cuboidgen.cli import app as gen_app
from cuboidtrain.cli import app as train_app
from tests.pages import ROOT, commands, shell_blocks, slug

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PROGRAMS = {"cuboidgen": gen_app, "cuboidtrain": train_app}
MAX_README = 15 * 1024


def cuboid_calls() -> list[tuple[str, str, list[str]]]:
    """Every (page, program, arguments) of a cuboidgen or cuboidtrain command in the pages' blocks."""
    calls = []
    for page in PAGES:
        for line in shell_blocks(page):
            for command in commands(line):
                for k, token in enumerate(command):
                    if Path(token).name in PROGRAMS:
                        calls.append((page.name, Path(token).name, command[k + 1:]))
                        break
    return calls


def parse(program: str, args: list[str]) -> None:
    """Parse `args` as `program` does, down to its subcommand; raises the command line's error."""
    command = typer.main.get_command(PROGRAMS[program])
    parent, name = None, program
    while args and hasattr(command, "commands") and args[0] in command.commands:
        parent = command.context_class(command, info_name=name, parent=parent)
        name, args = args[0], args[1:]
        command = command.commands[name]
    context = command.make_context(name, list(args), parent=parent)
    context.close()


CALLS = cuboid_calls()


def test_the_readme_is_short():
    assert len((ROOT / "README.md").read_bytes()) <= MAX_README


def test_the_pages_hold_commands_to_check():
    pages = {page for page, _, _ in CALLS}
    assert {"README.md", "generator.md", "training.md", "inference.md", "operations.md"} <= pages
    assert len(CALLS) > 50


@pytest.mark.parametrize("page, program, args", CALLS, ids=[f"{p}: {g} {' '.join(a)[:60]}" for p, g, a in CALLS])
def test_every_command_in_the_pages_parses(page, program, args):
    try:
        parse(program, args)
    except Exception as error:  # the command line's own error: a wrong option, value or choice
        message = getattr(error, "format_message", lambda: str(error))()
        pytest.fail(f"{page}: `{program} {shlex.join(args)}`: {message}")


def test_a_wrong_option_would_be_caught():
    with pytest.raises(Exception, match="No such option"):
        parse("cuboidtrain", ["infer", "m.png", "--no-such-option"])
    with pytest.raises(Exception, match="is not one of|invalid choice"):
        parse("cuboidgen", ["run", "--shape", "sphere"])


def test_make_targets_and_scripts_exist():
    makefile = (ROOT / "Makefile").read_text()
    for page in PAGES:
        for line in shell_blocks(page):
            for command in commands(line):
                words = [w for w in command if "=" not in w.split("/")[0]]  # VAR=value prefixes dropped
                if words[:1] == ["make"]:
                    for target in words[1:]:
                        assert re.search(rf"^{re.escape(target)}:", makefile, re.M), (page.name, target)
                for word in words:
                    if re.fullmatch(r"(recipes|benchmarks|ops)/[\w./-]+\.(sh|py)", word):
                        assert (ROOT / word).is_file(), (page.name, word)


def test_every_link_between_the_pages_lands():
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+://", target):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            assert file.exists(), (page.name, target)
            if anchor and file.suffix == ".md":
                headings = re.findall(r"^#+ (.*)$", file.read_text(), re.M)
                assert anchor in {slug(h) for h in headings}, (page.name, target)
