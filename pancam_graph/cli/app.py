"""The command line's application: the Typer app, the one place that turns the package's errors
into a message and an exit code (`_Commands.invoke`), and the console script `main`."""

from __future__ import annotations

import contextvars
import os
import sys
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.text import Text
from typer.core import TyperGroup

from ..errors import ConfigError, FolderInUse, InputError, PancamGraphError, RunInterrupted, WriteFailed

console = Console(stderr=True)
EXIT_USAGE = 2  # bad input: a file, a folder, an option
EXIT_FAILURE = 1  # the work itself failed
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
_USAGE_ERRORS = (ConfigError, InputError, FolderInUse)
_interrupt_reported = False  # a command said what Ctrl-C left behind: main() adds nothing
_rerun_stuck = False  # a recording failed: rerun's exit handler would wait for ever on it
# True while a command reads what the user gave it: whatever fails there is bad input (exit 2).
_reading_input: contextvars.ContextVar[bool] = contextvars.ContextVar("reading_input", default=False)


@contextmanager
def user_input():
    """The user's input is read in here: an error that escapes is theirs to fix (exit 2). On an
    error the flag stays set for `_Commands.invoke`, which resets it for the next command."""
    token = _reading_input.set(True)
    yield
    _reading_input.reset(token)


def _error(text: str) -> None:
    console.print(Text("error: ", style="bold red") + Text(text), soft_wrap=True)


class _Commands(TyperGroup):
    """Every command runs through `invoke`: the package's typed errors become one line and an
    exit code, here and nowhere else."""

    def list_commands(self, ctx) -> list[str]:
        return sorted(super().list_commands(ctx), key=lambda name: name != "run")  # the main job first

    def invoke(self, ctx):
        _reading_input.set(False)
        try:
            return super().invoke(ctx)
        except RunInterrupted as exc:
            global _interrupt_reported
            console.print(Text("interrupted: ", style="bold red") + Text(str(exc)), soft_wrap=True)
            _interrupt_reported = True
            raise typer.Exit(EXIT_INTERRUPTED) from None
        except PancamGraphError as exc:
            _error(str(exc))
            bad_input = (_reading_input.get() and not isinstance(exc, WriteFailed)) or isinstance(exc, _USAGE_ERRORS)
            raise typer.Exit(EXIT_USAGE if bad_input else EXIT_FAILURE) from None


# rich_markup_mode=None: usage errors as click's plain "Error: ..." line, not a box; user text
# (file names with [brackets]) is never parsed as markup.
app = typer.Typer(cls=_Commands, add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                  pretty_exceptions_enable=False, help="Rover localization over long traverses with a GTSAM factor "
                  "graph.")


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        print(f"pancam-graph {version('pancam-graph')}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="print the version and exit")) -> None:
    """Rover localization over long traverses with a GTSAM factor graph."""



def leave_without_rerun() -> None:
    """A rerun recording failed (a full disk, a viewer that stopped reading): rerun's exit
    handler would wait for it for ever, so the process ends without it once all is written."""
    global _rerun_stuck
    _rerun_stuck = True


def main() -> None:
    """The console script: Ctrl-C and the operating system's errors as one line and an exit code
    (the package's own errors are `_Commands.invoke`'s)."""
    # rerun's own log lines about a recording it cannot write: the command says it in one line
    os.environ.setdefault("RUST_LOG", "warn,re_log_encoding=off,re_sdk=off,re_grpc_client=off")
    try:
        _app_until_exit()
    except SystemExit as exc:
        if _rerun_stuck:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(exc.code if isinstance(exc.code, int) else EXIT_FAILURE)
        raise


def _app_until_exit() -> None:
    try:
        app()
    except KeyboardInterrupt:
        console.print(Text("interrupted", style="bold red"))
        raise SystemExit(EXIT_INTERRUPTED) from None
    except SystemExit as exc:  # typer turns Ctrl-C into a silent exit 130
        if exc.code == EXIT_INTERRUPTED and not _interrupt_reported:
            console.print(Text("interrupted", style="bold red"))
        raise
    except OSError as exc:  # a full disk, a permission: one line, not a traceback
        _error(f"{exc.filename}: {exc.strerror or exc}" if exc.filename else exc.strerror or str(exc))
        raise SystemExit(EXIT_FAILURE) from None
