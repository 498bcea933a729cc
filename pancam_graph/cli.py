"""Command line: parses arguments into library calls (api.py, bench.py), prints what they return
and chooses exit codes. The one place that catches the package's errors is `_Commands.invoke`."""

from __future__ import annotations

import contextvars
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text
from typer.core import TyperGroup

from .errors import ConfigError, FolderInUse, InputError, PancamGraphError

if TYPE_CHECKING:  # the heavy imports wait until a command needs them: --help stays fast
    from .api import RunOutcome
    from .frontend.calibrate import StereoFit
    from .stereo_pair import StereoCalibration
    from .viz.rerun_sink import RerunTarget

console = Console(stderr=True)
EXIT_USAGE = 2  # bad input: a file, a folder, an option
EXIT_FAILURE = 1  # the work itself failed
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
_USAGE_ERRORS = (ConfigError, InputError, FolderInUse)
_interrupt_reported = False  # a command said what Ctrl-C left behind: main() adds nothing
# True while a command reads what the user gave it: whatever fails there is bad input (exit 2).
_reading_input: contextvars.ContextVar[bool] = contextvars.ContextVar("reading_input", default=False)


@contextmanager
def _input():
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

    def invoke(self, ctx):
        from .api import RunInterrupted

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
            bad_input = _reading_input.get() or isinstance(exc, _USAGE_ERRORS)
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


# -- progress and Ctrl-C --------------------------------------------------------------------

def _progress_bar(quiet: bool = False) -> Progress:
    """Every long step's bar: what, how far, time so far and the time left."""
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("eta"), TimeRemainingColumn(), console=console, transient=True, disable=quiet)


def _with_progress(name: str, quiet: bool, work: Callable[[Callable[[str, int, int], None]], Any]) -> Any:
    """Run `work(progress)` under a progress bar labelled `name`; Ctrl-C stops it at its next
    report."""
    with _progress_bar(quiet) as bar, _ctrl_c_at_reports() as check:
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

def _load(scenario: str):
    from .config import load_scenario, resolve_scenario

    return load_scenario(resolve_scenario(scenario))


def _rerun_help(default_file: str) -> str:
    return (f"rerun viewer: 'spawn', 'save' ({default_file} in the results folder), 'save:FILE.rrd', "
            "'serve' (gRPC + web viewer), 'connect:URL' (a running viewer, e.g. rerun+http://host:9876/proxy)")


def _rerun_target(text: str | None, memory_limit: str) -> RerunTarget | None:
    """Parse --rerun; bad values are usage errors. `save` alone leaves the path to the library."""
    from .viz.rerun_sink import RerunTarget

    if text is None:
        return None
    mode, _, arg = text.partition(":")
    if mode == "spawn" and not arg:
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise ConfigError("--rerun spawn: no display (DISPLAY is not set); use --rerun save (then open the "
                              ".rrd elsewhere) or --rerun serve (a web viewer)")
        return RerunTarget(mode, memory_limit=memory_limit)
    if mode == "serve" and not arg:
        return RerunTarget(mode, memory_limit=memory_limit)
    if mode == "save":
        if arg and not arg.endswith(".rrd"):
            raise ConfigError(f"--rerun save:{arg}: the recording file must end in .rrd")
        return RerunTarget("save", path=Path(arg) if arg else None)
    if mode == "connect":
        return RerunTarget("connect", url=arg or None)
    raise ConfigError(f"--rerun {text!r}: expected spawn, save, save:FILE.rrd, serve or connect:URL")


def _serve_until_interrupted(url: str | None) -> None:
    import rerun as rr

    rr.serve_web_viewer(connect_to=url, open_browser=False)
    console.print(f"rerun: serving {url}; web viewer on http://localhost:9090 (Ctrl-C to stop)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def _parse_configs(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise ConfigError("--configs: give one or more configuration names or kinds joined by '+', "
                          "separated by commas (e.g. vo,vo+gps)")
    return names


def _topics(text: str | None) -> tuple[str, str] | None:
    if text is None:
        return None
    topics = [t.strip() for t in text.split(",") if t.strip()]
    if len(topics) != 2:
        raise ConfigError(f"--stereo-topics {text!r}: expected LEFT,RIGHT (two image topics)")
    return topics[0], topics[1]


def _detector(text: str | None) -> str | None:
    if text is not None and text not in ("gftt", "orb", "sift"):
        raise ConfigError(f"--detector {text!r}: expected gftt, orb or sift")
    return text


# -- run --------------------------------------------------------------------------------------

def _summary_table(outcome: RunOutcome) -> Table:
    """One row per configuration; narrow enough for an 80-column terminal."""
    from rich import box

    result = outcome.result
    held = any(c.holdout is not None for c in result.configurations.values())
    table = Table(title=f"{escape(result.name)} (seed {result.seed}, {len(result.traverse.stops)} stops)",
                  box=box.SIMPLE_HEAD, padding=(0, 1), caption="m: metres against the reference; GPS m: average "
                  "error against the fixes in the graph" + ("; held m: RMS 2-D to the held-out fixes" if held else ""))
    table.add_column("config", justify="left", no_wrap=True)
    for col in ["avg m", "clos. %", "ATE m", "length", "bridged", "GPS m"] + (["held m"] if held else []):
        table.add_column(col, justify="right")
    for name, c in result.configurations.items():
        m, vs = c.metrics, c.metrics_vs_gps
        cells = ["-"] * 4 if m is None else [f"{m.average_error_m:.2f}", f"{m.relative_closure_pct:.3f}",
                                             f"{m.ate_rmse_m:.2f}", f"{m.length_ratio:.4f}"]
        row = [name, *cells, str(c.bridged_stops), "-" if vs is None else f"{vs.average_error_m:.2f}"]
        if held:
            row.append("-" if c.holdout is None else f"{c.holdout.rms_2d_m:.3f}")
        table.add_row(*row)
    return table


def _print_outcome(outcome: RunOutcome) -> None:
    for warning in outcome.warnings:
        console.print(Text("warning: ", style="bold yellow") + Text(warning))
    Console(width=80).print(_summary_table(outcome))
    sys.stdout.flush()
    for name, reason in outcome.result.skipped.items():
        console.print(Text(f"not run: {name} ({reason})", style="dim"))
    saved = (f" ({outcome.checkpoints} checkpoints saved in {outcome.checkpoint_s:.1f} s)"
             if outcome.checkpoints else "")
    console.print(f"wall {outcome.result.wall_s:.1f} s{saved}; results in {outcome.folder} "
                  f"(report: {outcome.report})")
    recording = outcome.recording
    if recording is not None and recording.target.mode == "save":
        shown = recording.target.path
        console.print(f"rerun recording: {shown} (open with `rerun {shown}` or `pancam-graph view "
                      f"{outcome.folder}`)")
    if recording is not None and recording.target.mode == "serve":
        _serve_until_interrupted(recording.served_url)


@app.command("run")
def run_command(
    source: str | None = typer.Argument(None, help="bundled scenario name, a scenario TOML file, an "
                                        "observation folder, a ROS bag or a KITTI raw drive folder "
                                        "[default: denver_trail]"),
    out: Path | None = typer.Option(None, "--out", help="results folder (default: results/<name>-<time>)"),
    seed: int | None = typer.Option(None, "--seed", min=0, help="scenario: override its seed"),
    configs: str | None = typer.Option(None, "--configs", help="configurations to run, comma-separated: names "
                                       "(vo, vo_sites, full, ...) or kinds joined by '+' (vo+gps); default: "
                                       "every configuration the source can feed"),
    batch: bool = typer.Option(False, "--batch", help="polish every estimate with batch Levenberg-Marquardt"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    rerun: str | None = typer.Option(None, "--rerun", help=_rerun_help("recording.rrd")),
    viewer_memory: str = typer.Option("25%", "--viewer-memory", help="memory limit of a spawned or served viewer"),
    gps_topic: str | None = typer.Option(None, "--gps-topic", help="bag: NavSatFix topic (default: the only one)"),
    odom_topic: str | None = typer.Option(None, "--odom-topic", help="bag: Odometry topic (default: the only one)"),
    holdout_every: int | None = typer.Option(None, "--holdout-every", min=0,
                                             help="bag, KITTI: keep every N-th fix out of the graph for scoring "
                                                  "(default 5; 0: use all)"),
    geoid_height: float | None = typer.Option(None, "--geoid-height", help="KITTI: geoid height (m) added to "
                                                                           "OXTS alt"),
    detector: str | None = typer.Option(None, "--detector", help="image sources: gftt (default), orb or sift"),
    stereo_topics: str | None = typer.Option(None, "--stereo-topics", help="bag: LEFT,RIGHT rectified image "
                                             "topics for stereo VO (CameraInfo beside each: .../camera_info)"),
    skip_bad_frames: bool = typer.Option(False, "--skip-bad-frames", help="image folder: a missing, truncated "
                                         "or wrong-sized image leaves its stop to the VO bridge (default: stop "
                                         "with a message naming the file)"),
    resume: Path | None = typer.Option(None, "--resume", help="go on with a run that was killed (kill -9, power "
                                       "loss, out of memory) from its last checkpoint: its <out>.partial folder; "
                                       "the run keeps its own source and options"),
    no_plots: bool = typer.Option(False, "--no-plots", help="no PNG figures (1-2 s per run: sweeps skip them)"),
    one_process: bool = typer.Option(False, "--one-process", help="run everything in this process (default: on "
                                     "traverses of 300 stops or more the configurations run in groups side by "
                                     "side, one process per core, and on other long ones the stereo VO goes "
                                     "ahead in a second process; sweeps run on every core already)"),
    checkpoint_every: float = typer.Option(30.0, "--checkpoint-every", min=0.0, help="seconds between the "
                                           "checkpoints saved for --resume (and at most 5 % of the run's time); "
                                           "0: at every site and every 25 stops"),
) -> None:
    """Solve a traverse with iSAM2 and evaluate it: every source goes through the same back-end.

    A scenario is simulated and compared with truth; an observation folder runs external
    observations; a ROS bag or a KITTI raw drive becomes a traverse with a stop at each GPS fix,
    scored on held-out fixes. Writes metrics.json, run.toml, trajectories (TUM, KITTI, WGS84 CSV,
    GeoJSON, KML), plots and report.md into the results folder; a failed run leaves
    <out>.partial with what was done, which `--resume` continues.
    """
    from . import api
    from .processes import cores, start_process_server
    from .sources import SourceOptions

    processes = 1 if one_process else None
    if resume is not None:
        given = {"SOURCE": source, "--out": out, "--seed": seed, "--configs": configs, "--batch": batch or None,
                 "--gps-topic": gps_topic, "--odom-topic": odom_topic, "--holdout-every": holdout_every,
                 "--geoid-height": geoid_height, "--detector": detector, "--stereo-topics": stereo_topics,
                 "--skip-bad-frames": skip_bad_frames or None}
        with _input():
            clash = [name for name, value in given.items() if value is not None]
            if clash:
                raise ConfigError(f"--resume goes on with the run's own source and options; drop {', '.join(clash)}")
            target = _rerun_target(rerun, viewer_memory)
            point = api.resume_point(resume)
        n = len(point.data.traverse.stops)
        where = (f"at stop {point.states[0].next_stop}" if len(point.states) == 1 else "with its groups of "
                 "configurations at " + ", ".join(f"stop {s.next_stop} ({', '.join(s.localizers)})"
                                                  for s in point.states))
        console.print(f"resuming {point.data.traverse.name} {where} of {n} (from {point.partial})")
        _print_outcome(_with_progress(point.data.traverse.name, quiet, lambda report: api.resume(
            point, processes=processes, rerun=target, checkpoint_every_s=checkpoint_every, figures=not no_plots,
            progress=report)))
        return
    source = source or "denver_trail"
    if processes is None and cores() > 1:
        start_process_server()  # it imports the package while the source loads
    with _input():
        target = _rerun_target(rerun, viewer_memory)
        options = SourceOptions(seed, gps_topic, odom_topic, holdout_every, geoid_height, _detector(detector),
                                skip_bad_frames or None, _topics(stereo_topics))
        names = _parse_configs(configs)
        api.check_out(out)
        data = _with_progress(Path(source).name or source, quiet,
                              lambda report: api.open_data(source, options, out, report))
        from .solve.pipeline import select_configurations

        select_configurations(data.estimator, data.traverse, names)  # before anything is written
    for reason in data.rejected[:10]:
        console.print(Text("fix left out: ", style="yellow") + Text(reason))
    if len(data.rejected) > 10:
        console.print(Text(f"... {len(data.rejected) - 10} more fixes left out", style="yellow"))
    _print_outcome(_with_progress(data.traverse.name, quiet, lambda report: api.run(
        source, out=out, seed=seed, configs=names, batch=batch, processes=processes, rerun=target,
        checkpoint_every_s=checkpoint_every, figures=not no_plots, progress=report, opened=data)))


# -- the other commands -----------------------------------------------------------------------

@app.command("track")
def track_command(
    source: str = typer.Argument(..., help="stereo images: a KITTI odometry sequence folder"),
    out: Path = typer.Option(..., "--out", help="observation folder to write (docs/observation_format.md)"),
    detector: str | None = typer.Option(None, "--detector", help="gftt (default), orb or sift"),
    skip_bad_frames: bool = typer.Option(False, "--skip-bad-frames", help="a missing, truncated or wrong-sized "
                                         "image leaves its stop without observations (default: stop with a "
                                         "message naming the file)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Run the image front-end and write what it found as an observation folder, so the back-end
    can be run again (`pancam-graph run OUT`) without the images."""
    from . import api

    with _input():
        traverse = _with_progress(Path(source).name, quiet, lambda report: api.track(
            source, out, detector=_detector(detector), skip_bad_frames=skip_bad_frames, progress=report))
    frames = [len(s.stereo) for s in traverse.stops]
    console.print(f"{len(frames)} frames, median {sorted(frames)[len(frames) // 2]} features per frame; "
                  f"observations in {out}")


@app.command("render")
def render_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or a scenario TOML file"),
    out: Path = typer.Option(..., "--out", help="image folder to write (keep it out of git)"),
    seed: int | None = typer.Option(None, "--seed", min=0, help="override the scenario's seed"),
    control_field: bool = typer.Option(False, "--control-field", help="render the calibration control field "
                                       "instead, for `pancam-graph calibrate`"),
    views: int = typer.Option(8, "--views", min=3, max=100, help="with --control-field: stereo pairs to take"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Render a scenario's navigation stereo pairs and site panoramas (terrain with relief, rocks,
    texture at several scales, shading; the rig's intrinsics through a distorting lens on a
    slightly misaligned pair, with its calibration; sensor noise) into an image folder that `run`
    and `track` read; the truth goes in its own files. The scenario's [render] table sets the
    lens, the pair's errors, rocks and panoramas. Needs the [render] extra (moderngl on EGL).
    With --control-field: the same pair photographs a 3-D control field of 176 coded targets
    from several views (views/NN_left.png, NN_right.png, control_field.csv, and the pair's true
    calibration in truth_calibration.yaml)."""
    from .api import check_out

    with _input():
        check_out(out)
        sc = _load(scenario)
        start = time.perf_counter()
        if control_field:
            from .render.control_field import render_control_field

            n = _with_progress(sc.name, quiet, lambda report: render_control_field(sc, out, views, seed, report))
        else:
            from .render.images import render_scenario

            n = _with_progress(sc.name, quiet, lambda report: render_scenario(sc, out, seed, report))
    console.print(f"{n} images rendered into {out} in {time.perf_counter() - start:.0f} s")


@app.command("calibrate")
def calibrate_command(
    folder: Path = typer.Argument(..., help="control-field stereo pairs NAME_left.png / NAME_right.png (any depth)"),
    out: Path = typer.Option(..., "--out", help="OpenCV YAML to write: K1 D1 K2 D2 R T and the rectification "
                             "(R1 R2 P1 P2 Q), which `run` and `track` read as a calibration"),
    field: Path | None = typer.Option(None, "--field", help="the field's targets (target_id,panel,x_m,y_m,z_m); "
                                      "default FOLDER/control_field.csv"),
    truth: Path | None = typer.Option(None, "--truth", help="a calibration to compare with (default "
                                      "FOLDER/truth_calibration.yaml when there is one)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Calibrate a stereo pair from images of a 3-D control field (the seed's section 4.2): each
    camera's focal lengths, principal point and k1, k2, p1, p2, then the pair's boresight, and
    the rectification; prints the fit, its uncertainty and, given a truth, the errors."""
    from .formats.calibration import read_opencv_yaml, write_opencv_yaml
    from .formats.calibration_images import TRUTH_FILE, calibrate_folder

    with _input():
        if out.exists() and out.is_dir():
            raise ConfigError(f"--out {out}: is a folder; give the YAML file to write")
        truth = truth or (folder / TRUTH_FILE if (folder / TRUTH_FILE).is_file() else None)
        reference = read_opencv_yaml(truth) if truth is not None else None
        fit = _with_progress(folder.name, quiet, lambda report: calibrate_folder(folder, field, report))
        out.parent.mkdir(parents=True, exist_ok=True)
        write_opencv_yaml(out, fit.calibration, rectification=True)
    _print_calibration(fit, reference, truth)
    console.print(f"calibration written to {out}")


def _print_calibration(fit: StereoFit, reference: StereoCalibration | None, truth_path: Path | None) -> None:
    import cv2
    import numpy as np

    c = fit.calibration
    table = Table(title=f"{fit.views} views, {fit.left.targets} / {fit.right.targets} targets (left / right)",
                  box=None, padding=(0, 1))
    table.add_column("")
    columns = []

    def parameters(camera) -> list[float]:
        return [camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2, camera.p1, camera.p2]

    truths = reference.cameras() if reference is not None else (None, None)
    for name, camera, camera_fit, truth in zip(("left", "right"), c.cameras(), (fit.left, fit.right), truths,
                                              strict=True):
        table.add_column(name, justify="right")
        table.add_column("1 sigma", justify="right")
        columns += [parameters(camera), list(camera_fit.sigma[:8])]
        if truth is not None:
            table.add_column("- truth", justify="right")
            columns.append([a - b for a, b in zip(parameters(camera), parameters(truth), strict=True)])
    for row, label in enumerate(("fx px", "fy px", "cx px", "cy px", "k1", "k2", "p1", "p2")):
        fmt = "{:.2f}" if row < 4 else "{:.5f}"
        table.add_row(label, *(fmt.format(col[row]) for col in columns))
    extra = [""] * (len(columns) // 2 - 1)
    table.add_row("RMS px", f"{fit.left.rms_px:.3f}", *extra, f"{fit.right.rms_px:.3f}", *extra)
    table.add_row("dropped", str(fit.left.rejected), *extra, str(fit.right.rejected), *extra)
    console.print(table)
    rectified = c.rectified()
    line = (f"baseline {c.baseline_m * 1000:.2f} mm, stereo RMS {fit.stereo_rms_px:.3f} px; rectified focal length "
            f"{rectified.camera.fx:.2f} px")
    if reference is not None:
        angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(c.rotation @ reference.rotation.T)[0]))
        line += (f"\nagainst {truth_path}: baseline {(c.baseline_m - reference.baseline_m) * 1000:+.3f} mm, "
                 f"boresight {angle:.4f} deg, focal lengths {100 * (c.k_left[0, 0] / reference.k_left[0, 0] - 1):+.3f} "
                 f"/ {100 * (c.k_right[0, 0] / reference.k_right[0, 0] - 1):+.3f} %")
    console.print(line)


@app.command("show-config")
def show_config_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or a scenario TOML file"),
) -> None:
    """Print a scenario's resolved configuration (every default filled in) as TOML."""
    from .config import dump_scenario

    with _input():
        print(dump_scenario(_load(scenario)), end="")


@app.command("view")
def view_command(
    results: Path = typer.Argument(..., help="a results folder written by `pancam-graph run`"),
    rerun: str = typer.Option("spawn", "--rerun", help=_rerun_help("replay.rrd")),
    viewer_memory: str = typer.Option("25%", "--viewer-memory", help="memory limit of a spawned or served viewer"),
) -> None:
    """Replay a finished results folder into rerun with the live run's layout."""
    from .api import view
    from .store.results_folder import read_run

    with _input():
        target = _rerun_target(rerun, viewer_memory)
        saved = read_run(results)
    recording = view(results, target, saved)
    if recording.target.mode == "save":
        console.print(f"rerun recording: {recording.target.path}")
    elif recording.target.mode == "serve":
        _serve_until_interrupted(recording.served_url)


@app.command("eval")
def eval_command(
    estimate: Path = typer.Argument(..., help="estimated trajectory: TUM, KITTI poses or a GPS log"),
    reference: Path = typer.Argument(..., help="reference: TUM, KITTI poses or a GPS log (NMEA, GPX, CSV, KF-GINS)"),
    align: str = typer.Option("none", "--align", help="none | se3 | yaw: rigid alignment of the estimate first"),
    rpe_delta: float = typer.Option(10.0, "--rpe-delta", min=0.0, help="relative pose error over this many "
                                                                       "metres of reference path"),
    max_dt: float = typer.Option(0.01, "--max-dt", min=0.0, help="association: largest time difference, s"),
    origin: str | None = typer.Option(None, "--origin", help="LAT,LON,H of the ENU frame for GPS logs (default: "
                                                            "local_frame.json beside the estimate, else the "
                                                            "first fix)"),
    gps_sigma: float = typer.Option(1.0, "--gps-sigma", help="sigma for GPS logs that state none (unused by "
                                                             "the metrics)"),
    out: Path | None = typer.Option(None, "--out", help="write metrics.json (and a plot) into this folder"),
) -> None:
    """Compare two trajectories, or a trajectory with a GPS log, with the run's metrics."""
    from .api import evaluate

    with _input():
        frame = None
        if origin is not None:
            try:
                frame = tuple(float(v) for v in origin.split(","))
            except ValueError:
                frame = ()
            if len(frame) != 3:
                raise ConfigError(f"--origin {origin!r}: expected LAT,LON,H in degrees and metres")
        result = evaluate(estimate, reference, align=align, max_dt_s=max_dt, rpe_delta_m=rpe_delta, origin=frame,
                          gps_sigma_m=gps_sigma, out=out)
    m = result.metrics
    table = Table(title=escape(f"{estimate.name} vs {reference.name} ({len(result.reference)} matched, "
                               f"{result.association}, alignment {result.alignment})"))
    cells = {
        "ATE RMSE m": m.ate_rmse_m, "avg err m": m.average_error_m, "closure m": m.closure_error_m,
        "rel. closure %": m.relative_closure_pct, "length ratio": m.length_ratio,
        f"RPE {rpe_delta:g} m trans. RMSE m": m.rpe_translation_rmse_m,
        f"RPE {rpe_delta:g} m rot. RMSE deg": m.rpe_rotation_rmse_deg, "drift %": m.drift_translation_pct,
    }
    table.add_column("metric")  # one row per metric: fits an 80-column terminal
    table.add_column("value", justify="right")
    for name, value in cells.items():
        table.add_row(name, "-" if value is None else f"{value:.4f}")
    Console(width=80).print(table)
    if out is not None:
        console.print(f"metrics in {out / 'metrics.json'}, plot {out / 'eval.png'}")


@app.command("sweep")
def sweep_command(
    spec: Path = typer.Argument(..., help="sweep specification (TOML): scenarios, seeds, rigs, estimator variants"),
    out: Path = typer.Option(..., "--out", help="sweep folder: a results folder per run under runs/, and the tables; "
                             "run again on the same folder, it skips the runs already done"),
    workers: int = typer.Option(2, "--workers", min=1, help="local Dask cluster of this many workers"),
    scheduler: str | None = typer.Option(None, "--scheduler", help="an existing Dask cluster's scheduler address "
                                         "(tcp://host:8786) instead of a local one; its workers need "
                                         "pancam-graph and --out on a shared file system"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Run every combination of scenarios x rigs x estimator variants x seeds on Dask, one task
    per run, each writing its own results folder; then read their metrics into runs.csv and
    summary.csv (efficiency and ANEES over the seeds, as `bench --monte-carlo`). A run that
    fails or times out is recorded (runs_status.csv) and the others go on."""
    from .sweep.runner import run_sweep
    from .sweep.spec import load_spec, plan
    from .sweep.table import run_rows, summarize, write_tables

    with _input():
        sweep = load_spec(spec)
        runs = plan(sweep, out, spec.parent)
        (out / "sweep.toml").write_text(spec.read_text(encoding="utf-8"), encoding="utf-8")
    start = time.perf_counter()
    with _progress_bar(quiet) as bar:
        task = bar.add_task(f"{escape(spec.stem)}: runs", total=len(runs))

        def report(record, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)
            if record.status in ("failed", "timeout"):
                bar.console.print(Text(f"{record.run.name}: {record.status}: {record.message}", style="yellow"))

        records = run_sweep(runs, sweep.timeout_s, workers, scheduler, report)
    rows = run_rows(records)
    summary = summarize(rows)
    write_tables(out, records, rows, summary)
    table = Table(title=f"{escape(spec.stem)}: {len(runs)} runs", box=None, padding=(0, 1))
    for column in ("scenario", "rig", "variant", "config", "runs", "closure %", "ATE m", "efficiency", "ANEES"):
        table.add_column(column)
    for row in summary:
        table.add_row(escape(row.scenario), row.rig, escape(row.variant), escape(row.config), str(row.runs),
                      f"{row.closure_pct_mean:.3f}", f"{row.ate_m_mean:.2f}",
                      "-" if row.efficiency is None else f"{row.efficiency:.2f}",
                      "-" if row.anees is None else f"{row.anees:.2f} ({row.covariance})")
    Console(width=120).print(table)
    counts = {status: sum(r.status == status for r in records) for status in ("done", "skipped", "failed", "timeout")}
    console.print(f"wall {time.perf_counter() - start:.1f} s; " + ", ".join(f"{n} {k}" for k, n in counts.items())
                  + f"; tables in {out} (runs.csv, summary.csv, runs_status.csv)")
    if counts["failed"] or counts["timeout"]:
        raise typer.Exit(EXIT_FAILURE)


@app.command("bench")
def bench_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or path to a TOML file, or "
                                   "'frontend' to time the image front-end on SOURCE, or 'sites' to measure the "
                                   "site panoramas' matching on the image folder SOURCE"),
    source: str | None = typer.Argument(None, help="with 'frontend': stereo images (a KITTI odometry sequence); "
                                        "with 'sites': a rendered image folder"),
    detector: str | None = typer.Option(None, "--detector", help="with 'frontend': gftt, orb or sift"),
    seed: int | None = typer.Option(None, "--seed", help="first seed (default: the scenario's)"),
    seeds: int = typer.Option(1, "--seeds", min=1, help="run this many consecutive seeds and summarise"),
    rerun: bool = typer.Option(False, "--rerun", help="also time each run with `--rerun save` (alternating) "
                                                      "and report the overhead"),
    monte_carlo: int = typer.Option(0, "--monte-carlo", min=0, help="run this many seeds and report each "
                                    "configuration's efficiency (RMSE / CRLB) and ANEES with its chi-square band"),
    workers: int = typer.Option(0, "--workers", min=0, help="with --monte-carlo: run the seeds as a sweep on a "
                                "local Dask cluster of this many workers (0: one after another in this process)"),
    plot: Path | None = typer.Option(None, "--plot", help="also draw the first seed's cost along the path (iSAM2 "
                                     "update per km, peak memory) into this PNG"),
) -> None:
    """Time full runs (all configurations) and print one JSON object; `bench frontend SOURCE`
    times the image front-end per stage."""
    from . import bench

    def report(stage: str, done: int, total: int) -> None:
        if stage.startswith("seed "):  # a finished seed of several: one line each
            console.print(stage)

    if scenario in ("frontend", "sites"):
        with _input():
            if scenario == "sites":
                document = _with_progress("sites", False, lambda p: bench.bench_sites(source, progress=p))
            else:
                document = _with_progress("front-end", False, lambda p: bench.bench_frontend(
                    source, _detector(detector), progress=p))
    elif source is not None or detector is not None:
        raise ConfigError("SOURCE and --detector go with 'bench frontend' only")
    elif monte_carlo and workers:
        document = bench.bench_monte_carlo_sweep(scenario, seed, max(seeds, monte_carlo), workers)
    else:
        document = bench.bench_runs(scenario, seed, seeds, rerun, monte_carlo, plot,
                                    report if seeds > 1 or rerun or monte_carlo else None)
    print(json.dumps(document, indent=2))


@app.command("analyze")
def analyze_command(
    rig: list[str] = typer.Option(None, "--rig", help="rig preset (repeatable; default: every preset)"),
    out: Path = typer.Option(Path("results/analysis"), "--out", help="folder for analysis.json, "
                                                                     "table_3_2.md and the figures"),
    sigma_px: float = typer.Option(0.5, "--sigma-px", min=0.01, help="matching error of x_l and x_r (px)"),
    baseline: float | None = typer.Option(None, "--baseline", min=0.01, help="custom rig: stereo baseline (m)"),
    focal_px: float | None = typer.Option(None, "--focal-px", min=1.0, help="custom rig: focal length (px)"),
    fov_deg: float | None = typer.Option(None, "--fov", min=1.0, max=179.0, help="custom rig: horizontal FOV (deg)"),
) -> None:
    """The seed's Chapter 3 error analysis for each rig: mapping ellipses, two-stop VO, the HRC's
    gain and the two-site BA (optimal FOV, longest site spacing for 1 %), as figures, a Table 3.2
    and analysis.json; every assumption is written with them."""
    from .analysis.design import AnalysisRig, Assumptions
    from .analysis.trades import SEED_TABLE_3_2, analyze
    from .api import check_out
    from .rig import RIG_PRESETS
    from .viz.analysis_plots import write_analysis

    check_out(out)
    custom = [baseline, focal_px, fov_deg]
    if any(v is not None for v in custom) and not all(v is not None for v in custom):
        raise ConfigError("a custom rig needs --baseline, --focal-px and --fov together")
    try:
        if all(v is not None for v in custom):
            rigs = [AnalysisRig("custom", baseline, focal_px, fov_deg)]
        else:
            rigs = [AnalysisRig.preset(name) for name in (rig or list(RIG_PRESETS))]
    except ValueError as exc:
        raise ConfigError(f"--rig: {exc}") from None
    assumptions = Assumptions(sigma_px=sigma_px)
    start = time.perf_counter()
    rows = _with_progress("analysing rigs", False, lambda report: analyze(
        rigs, assumptions, progress=lambda done, total: report("rigs", done, total)))
    written = write_analysis(rows, assumptions, out)
    table = Table(title=f"two-site BA, {assumptions.tie_points} tie points, sigma {sigma_px} px")
    for column in ("rig", "optimal FOV deg", "FOV, 16 tie points", "max spacing for 1 % (m)", "seed (m)"):
        table.add_column(column, justify="right")
    for row in rows:
        seed = SEED_TABLE_3_2.get(row.name, {}).get("max_site_spacing_m", "-")
        table.add_row(row.name, f"{row.optimal_fov_deg:.0f}", f"{row.optimal_fov_16_deg:.0f}",
                      f"{row.max_site_spacing_m:.1f}", str(seed))
    console.print(table)
    console.print(f"{len(written)} files in {out} ({time.perf_counter() - start:.1f} s); "
                  f"assumptions and notes in {out / 'table_3_2.md'}")


@app.command("simulate")
def simulate_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or path to a TOML file"),
    out: Path = typer.Option(..., "--out", help="observation folder to write"),
    seed: int | None = typer.Option(None, "--seed", min=0, help="override the scenario's seed"),
    no_truth: bool = typer.Option(False, "--no-truth", help="leave the reference poses (truth.kitti) out"),
) -> None:
    """Write a scenario's simulated observations as an observation folder (docs/observation_format.md),
    the input an external front-end would give `pancam-graph run`."""
    from .api import simulate

    with console.status(f"simulating {escape(scenario)}"):
        traverse = simulate(scenario, out, seed=seed, truth=not no_truth)
    console.print(f"{len(traverse.stops)} stops written to {out}")


@app.command("scenarios")
def scenarios_command() -> None:
    """List the bundled scenarios."""
    from .config import bundled_scenarios, load_scenario

    for name, path in sorted(bundled_scenarios().items()):
        try:
            description = load_scenario(path).description
        except ConfigError as exc:  # listed anyway, with its problem
            description = f"(invalid: {exc})"
        print(f"{name:16s} {description}")


def main() -> None:
    """The console script: Ctrl-C and the operating system's errors as one line and an exit code
    (the package's own errors are `_Commands.invoke`'s)."""
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
        _error(f"{exc.filename or ''}: {exc.strerror or exc}")
        raise SystemExit(EXIT_FAILURE) from None


if __name__ == "__main__":
    main()
