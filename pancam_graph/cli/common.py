"""What the commands share: progress bars, Ctrl-C at a progress report, and parsing of the
options several commands take. Errors are the package's typed ones (app.py prints them)."""

from __future__ import annotations

import functools
import inspect
import ipaddress
import os
import signal
import threading
import time
import typing
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..config import SourceOptions
from ..errors import ConfigError
from .app import console, user_input

if TYPE_CHECKING:  # the heavy imports wait until a command needs them: --help stays fast
    from ..viz.rerun_sink import RerunTarget


def progress_bar(quiet: bool = False) -> Progress:
    """Every long step's bar: what, how far, time so far and the time left."""
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("eta"), TimeRemainingColumn(), console=console, transient=True, disable=quiet)


def with_progress(name: str, quiet: bool, work: Callable[[Callable[[str, int, int], None]], Any]) -> Any:
    """Run `work(progress)` under a progress bar labelled `name`; Ctrl-C stops it at its next
    report."""
    with progress_bar(quiet) as bar, _ctrl_c_at_reports() as check:
        task = bar.add_task(f"{escape(name)}: stops", total=None)

        def report(stage: str, done: int, total: int) -> None:
            check()
            bar.update(task, description=f"{escape(name)}: {escape(stage)}", completed=done, total=total)

        return work(report)


@contextmanager
def _ctrl_c_at_reports():
    """Ctrl-C raises KeyboardInterrupt at the work's next progress report (a stop), not
    wherever it lands: inside GTSAM's call of a Python factor it was lost and the run went on.
    A second Ctrl-C stops at once."""
    pressed = []

    def handler(signum, frame):
        if pressed:
            raise KeyboardInterrupt
        pressed.append(signum)

    def check() -> None:
        if pressed:
            raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():  # signals go to the main thread only
        yield check
        return
    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)


# -- parsing ----------------------------------------------------------------------------------

def load_named_scenario(scenario: str, errors: str | None = None):
    from ..config import load_scenario, resolve_scenario

    return load_scenario(resolve_scenario(scenario), errors)


def rerun_help(default_file: str) -> str:
    return (f"rerun viewer: 'spawn', 'save' ({default_file} in the results folder), 'save:FILE.rrd', "
            "'serve' (a web viewer on 127.0.0.1; 'serve:0.0.0.0' on every interface), 'connect:URL' (a running "
            "viewer, e.g. rerun+http://host:9876/proxy)")


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def rerun_target(text: str | None, memory_limit: str) -> RerunTarget | None:
    """Parse --rerun; bad values are usage errors. `save` alone leaves the path to the library."""
    from ..viz.rerun_sink import RerunTarget

    if text is None:
        return None
    mode, _, arg = text.partition(":")
    if mode == "spawn" and not arg:
        if not has_display():
            raise ConfigError("--rerun spawn: no display (DISPLAY is not set); use --rerun save (then open the "
                              ".rrd elsewhere) or --rerun serve (a web viewer)")
        return RerunTarget(mode, memory_limit=memory_limit)
    if mode == "serve":
        try:
            ipaddress.ip_address(arg or "127.0.0.1")
        except ValueError:
            raise ConfigError(f"--rerun serve:{arg}: expected an address to listen on, e.g. serve:0.0.0.0 "
                              "(every interface); plain serve listens on 127.0.0.1") from None
        return RerunTarget(mode, memory_limit=memory_limit, host=arg or "127.0.0.1")
    if mode == "save":
        if arg and not arg.endswith(".rrd"):
            raise ConfigError(f"--rerun save:{arg}: the recording file must end in .rrd")
        return RerunTarget("save", path=Path(arg) if arg else None)
    if mode == "connect":
        return RerunTarget("connect", url=arg or None)
    raise ConfigError(f"--rerun {text!r}: expected spawn, save, save:FILE.rrd, serve, serve:ADDRESS or connect:URL")


def serve_until_interrupted(recording, serve_for_s: float | None) -> None:
    """Keep the recording's web viewer up after the run: until Ctrl-C, or for `serve_for_s`."""
    how_long = "Ctrl-C to stop" if serve_for_s is None else f"for {serve_for_s:g} s; Ctrl-C to stop sooner"
    console.print(f"rerun: the web viewer stays at {recording.viewer_url} ({how_long})", soft_wrap=True)
    end = None if serve_for_s is None else time.monotonic() + serve_for_s
    try:
        while recording.serving and (end is None or time.monotonic() < end):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        recording.stop_serving()


SERVE_FOR_HELP = "with --rerun serve: keep the web viewer up this many seconds after the run (default: until Ctrl-C)"


def announce_viewer(viewer_url: str) -> None:
    console.print(f"rerun: web viewer at {viewer_url} (it fills in as the recording comes)", soft_wrap=True)


def parse_configs(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise ConfigError("--configs: give one or more configuration names or kinds joined by '+', "
                          "separated by commas (e.g. vo,vo+gps)")
    return names


def with_source_options(*names: str):
    """The command takes the flags of these SourceOptions (source_options.py says each one's flag,
    help and checks) and receives them as one `source_options` argument, checked as user input."""

    def decorate(command: Callable) -> Callable:
        hints = typing.get_type_hints(command)
        own = [p.replace(annotation=hints[p.name]) for p in inspect.signature(command).parameters.values()
               if p.name != "source_options"]
        flags = SourceOptions.flags()
        added = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=_text_type(name),
                                   default=typer.Option(None, flags[name], help=SourceOptions.help(name),
                                                        min=SourceOptions.minimum(name)))
                 for name in names]

        @functools.wraps(command)
        def with_options(**kwargs):
            given = {name: kwargs.pop(name) for name in names}
            with user_input():
                # an unset flag is None (False for a switch): not given
                options = SourceOptions(**{k: v for k, v in given.items() if v is not None and v is not False})
            return command(**kwargs, source_options=options)

        del with_options.__wrapped__  # typer reads the signature below, not the command's
        with_options.__annotations__ = {}
        with_options.__signature__ = inspect.Signature(own + added)
        return with_options

    return decorate


def _text_type(name: str) -> type:
    """An option's type on the command line: its own, or text it parses (stereo topics)."""
    value = typing.get_type_hints(SourceOptions)[name]
    kept = [t for t in typing.get_args(value) if t is not type(None)]
    return kept[0] if kept and kept[0] in (int, float, bool) else str


def examples(*commands: str) -> str:
    """A command's --help epilog: its examples, one a line, kept as written (click's \\b)."""
    return "\b\nExamples:\n" + "\n".join(f"  {command}" for command in commands)
