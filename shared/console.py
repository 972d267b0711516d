"""What both command lines share: the stderr console, logging set-up, one-line failures."""
from __future__ import annotations

import logging
import os
import select
import sys
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
    # torch's own INFO lines (its FakeTensor cache statistics at exit, after a Ctrl-C during its
    # import) are not ours to show; its warnings still are
    logging.getLogger("torch").setLevel(logging.DEBUG if verbose else logging.WARNING)


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
    is not one of ...": the prefix is dropped here, where the subcommand's options are parsed.
    A reader that closed our stdout (`| head`) ends the command quietly (`PIPE_CLOSED`)."""

    def main(self, *args, **kwargs):
        # rich's documented hook for a closed pipe (its own exits 1), for every console this command makes
        Console.on_broken_pipe = lambda console: quit_quietly()
        try:
            result = super().main(*args, **kwargs)
        except SystemExit as exit:
            # typer met a closed pipe where it prints plainly: it wrapped the streams and exits 1
            code = PIPE_CLOSED if type(sys.stdout).__name__ == "PacifyFlushWrapper" else exit.code
            flush_or_quit()  # what is still buffered, before the interpreter's own flush at exit
            raise SystemExit(code) from None
        flush_or_quit()
        return result

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except typer.BadParameter as exc:
            exc.message = plain_message(exc.message)
            raise
        except (UsageError, OSError) as exc:
            if isinstance(exc, BrokenPipeError) and reader_gone():
                quit_quietly()
            fail(str(exc))


PIPE_CLOSED = 141  # a command whose reader went away ends as SIGPIPE would end it: 128 + 13, nothing said


def reader_gone() -> bool:
    """Whether stdout's or stderr's reader closed its end of the pipe (a BrokenPipeError from
    elsewhere, a socket, stays an error)."""
    return closed_pipe(1) or closed_pipe(2)


def closed_pipe(fd: int) -> bool:
    """Whether `fd` is a pipe whose reader is gone: poll says POLLERR for it (where there is no
    poll, Windows, it is assumed)."""
    if not hasattr(select, "poll"):
        return True
    poller = select.poll()
    try:
        poller.register(fd, select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (OSError, ValueError):
        return False


def quit_quietly():
    """End now, silently, exit PIPE_CLOSED: the closed streams point at /dev/null, so that
    nothing left to print (a summary, the interpreter's flush at exit) fails again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for fd in (1, 2):
        if closed_pipe(fd):
            os.dup2(devnull, fd)
    os.close(devnull)
    raise SystemExit(PIPE_CLOSED)


def flush_or_quit() -> None:
    """Flush stdout; a reader gone meanwhile ends the command as `quit_quietly` does."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        quit_quietly()
    except (OSError, ValueError):  # closed, or not ours to report
        pass


def plain_message(message: str) -> str:
    """A validation message without pydantic's kind prefix ("Value error, ...")."""
    for prefix in ("Value error, ", "Assertion failed, "):
        if message.startswith(prefix):
            return message[len(prefix):]
    return message
