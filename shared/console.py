"""What both command lines share: the stderr console, logging set-up, one-line failures."""
from __future__ import annotations

import logging
import os
import select
import sys
from enum import Enum
from typing import get_args

import typer
from rich.markup import escape
from rich.console import Console
from rich.logging import RichHandler
# typer's own copy of click (typer._click): the exceptions a command line meets are these
from typer._click.exceptions import BadOptionUsage, BadParameter, ClickException
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption

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


def say(line: str) -> None:
    """One line on stderr as written (markup aside): not highlighted, and never wrapped, for off a
    terminal rich wraps at 80 columns, and a path broken across two lines can no longer be copied."""
    console.print(line, highlight=False, soft_wrap=True)


def fail(message: str, code: int = 2) -> None:
    """One line on stderr and a non-zero exit (2: a bad value): how every error is reported."""
    # escape: a message quotes values such as [nan, 1.0], which rich would read as markup and drop
    say(f"[red]error:[/red] {escape(message)}")
    raise typer.Exit(code)


class PlainHelp:
    """`--help` that reads as a command line's usually does. typer (0.29) writes a type after every
    option, `<bool>` after a flag too (`--help <bool>`), and a required argument in braces in the
    usage line (`{SPOOL} {OUT_DIR}`): a flag takes no value, and an argument reads as click writes
    it, SPOOL, [PATH]... A mixin of `Command` and `Commands`, so every command and group of both
    command lines gets it (`CLI`)."""

    def get_params(self, ctx):
        params = super().get_params(ctx)
        for param in params:
            if isinstance(param, TyperOption) and param.is_flag and param.metavar is None:
                param.metavar = ""  # the type column's text for it; its error hints name the flag itself
        return params


def usage_name(argument: TyperArgument) -> str:
    """An argument in the usage line as click writes it: NAME, [NAME] when optional, ... when repeated."""
    name = argument.metavar or argument.name.upper()
    return (name if argument.required else f"[{name}]") + ("..." if argument.nargs != 1 else "")


class Command(PlainHelp, TyperCommand):
    """A subcommand of either command line (`CLI.command`)."""

    def collect_usage_pieces(self, ctx) -> list[str]:
        arguments = [usage_name(p) for p in self.get_params(ctx) if isinstance(p, TyperArgument)]
        return ([self.options_metavar] if self.options_metavar else []) + arguments


class Commands(PlainHelp, TyperGroup):
    """A command line whose errors give the message alone, in one line.

    The one place both command lines (`CLI`) report what the user got wrong:
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
        words = [*ctx._protected_args, *ctx.args]  # the subcommand's, before it parses them (and may fail)
        try:
            return super().invoke(ctx)
        except (BadParameter, BadOptionUsage) as exc:
            option = several_values_option(exc, self.get_command(ctx, words[0]) if words else None)
            if option is not None:  # `--principal-px 320 mask.png`: the file taken as Y, or nothing after it
                fail(several_values_message(option, words))
            if isinstance(exc, BadParameter):
                exc.message = plain_message(exc.message)
            raise
        except (UsageError, OSError) as exc:
            if isinstance(exc, BrokenPipeError) and reader_gone():
                quit_quietly()
            fail(str(exc))


class CLI(typer.Typer):
    """A typer app of `Commands`, its commands `Command`s: how both command lines and their groups
    are made, so each gets the same errors and help."""

    def __init__(self, **kwargs):
        super().__init__(**{"cls": Commands, **kwargs})

    def command(self, name: str | None = None, *, cls: type[TyperCommand] | None = None, **kwargs):
        return super().command(name, cls=cls or Command, **kwargs)


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


NUMBER_WORDS = {2: "two", 3: "three", 4: "four"}


def several_values_option(exc: ClickException, command) -> TyperOption | None:
    """The option of several values (`--principal-px X Y`) of `command` that `exc` is about, else None."""
    option = getattr(exc, "param", None)
    if option is None and isinstance(exc, BadOptionUsage) and command is not None:
        option = next((p for p in command.params if exc.option_name in p.opts), None)
    return option if isinstance(option, TyperOption) and option.nargs > 1 else None


def several_values_message(option: TyperOption, words: list[str]) -> str:
    """`--principal-px 320 mask.png: expected two numbers X Y`: the option as typed, the words it
    took (up to its count, none of them another option), and what it needs."""
    at = max((k for k, w in enumerate(words) if w in option.opts), default=None)  # its last use: the bad one
    name, taken = (option.opts[0], []) if at is None else (words[at], words[at + 1:at + 1 + option.nargs])
    taken = taken[:next((k for k, w in enumerate(taken) if w.startswith("--")), len(taken))]
    kinds = set(get_args(option.type_descriptor.annotation))
    what = "numbers" if kinds and kinds <= {int, float} else "values"
    count = NUMBER_WORDS.get(option.nargs, str(option.nargs))
    return f"{' '.join([name, *taken])}: expected {count} {what} {option.metavar or ''}".rstrip()


def plain_message(message: str) -> str:
    """A validation message without pydantic's kind prefix ("Value error, ...")."""
    for prefix in ("Value error, ", "Assertion failed, "):
        if message.startswith(prefix):
            return message[len(prefix):]
    return message
