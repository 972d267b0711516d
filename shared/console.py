"""What both command lines share: the stderr console, logging set-up, one-line failures."""
from __future__ import annotations

import logging
from enum import Enum

import typer
from rich.markup import escape
from rich.console import Console
from rich.logging import RichHandler
from typer.core import TyperGroup

from shared.errors import UsageError


def choices(name: str, values) -> type[Enum]:
    """A click choice of a library's own list, so the command line and the library cannot drift apart."""
    return Enum(name, {value: value for value in values}, type=str)

console = Console(stderr=True)
# Columns a live dashboard leaves free on the right: a terminal echoes Ctrl-C as "^C" after
# the panel's last line; were that line full width, the echo would wrap onto a new line and
# the next redraw would start one line too low, leaving the top border printed twice.
ECHO_ROOM = 2


def setup_logging(verbose: bool = False) -> None:
    if console.is_terminal:
        handler = RichHandler(console=console, show_path=False)
        handler.setFormatter(logging.Formatter("%(message)s"))  # rich adds time and level itself
    else:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler], force=True)


def fail(message: str, code: int = 2) -> None:
    """One line on stderr and a non-zero exit (2: a bad value): how every error is reported."""
    # escape: a message quotes values such as [nan, 1.0], which rich would read as markup and drop
    console.print(f"[red]error:[/red] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


class Commands(TyperGroup):
    """A command line whose errors give the message alone, in one line.

    The one place both command lines (`Typer(cls=Commands)`) report what the user got wrong:
    a UsageError (a bad option, file, model, mask, spool) or an OSError (a path that cannot be
    read or written) from any subcommand becomes `fail`'s one line and exit 2. typer checks a
    value with pydantic and passes on pydantic's wording of a rejected one, "Value error, '3'
    is not one of ...": the prefix is dropped here, where the subcommand's options are parsed."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except typer.BadParameter as exc:
            exc.message = plain_message(exc.message)
            raise
        except (UsageError, OSError) as exc:
            fail(str(exc))


def plain_message(message: str) -> str:
    """A validation message without pydantic's kind prefix ("Value error, ...")."""
    for prefix in ("Value error, ", "Assertion failed, "):
        if message.startswith(prefix):
            return message[len(prefix):]
    return message
