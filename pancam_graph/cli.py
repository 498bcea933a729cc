"""Command line: the only place that parses arguments, prints and chooses exit codes."""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

from .errors import ConfigError, FolderInUse, FrameError, InputError, PancamGraphError, ResultsError, ViewerUnavailable
from .processes import cores

if TYPE_CHECKING:  # the heavy imports wait until a command needs them: --help stays fast
    from .frontend.calibrate import StereoFit
    from .group import RunState
    from .results import RunOptions, RunResult
    from .sources import SourceData
    from .stereo_pair import StereoCalibration

# rich_markup_mode=None: usage errors as click's plain "Error: ..." line, not a box; user text
# (file names with [brackets]) is never parsed as markup.
app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None, pretty_exceptions_enable=False,
                  help="Rover localization over long traverses with a GTSAM factor graph.")
console = Console(stderr=True)
EXIT_USAGE = 2  # bad input: a file, a folder, an option
EXIT_FAILURE = 1  # the run itself failed
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
_USAGE_ERRORS = (ConfigError, InputError, FolderInUse)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        print(f"pancam-graph {version('pancam-graph')}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="print the version and exit")) -> None:
    """Rover localization over long traverses with a GTSAM factor graph."""


def _start_process_server(options) -> None:
    """Worker processes come from a server that imports the package once: start it now, so it
    imports while the source loads (processes.py)."""
    if options.processes > 1:
        from .processes import start_process_server

        start_process_server()


def _fail(exc: PancamGraphError, bad_input: bool = False) -> typer.Exit:
    """Print the error (as plain text: user text may contain [brackets]) and choose the exit code."""
    console.print(Text("error: ", style="bold red") + Text(str(exc)), soft_wrap=True)
    return typer.Exit(EXIT_USAGE if bad_input or isinstance(exc, _USAGE_ERRORS) else EXIT_FAILURE)


def _load(scenario: str):
    from .config import load_scenario, resolve_scenario

    return load_scenario(resolve_scenario(scenario))


ProgressCallback = Callable[[str, int, int], None]


def _progress_bar(quiet: bool = False) -> Progress:
    """Every long step's bar: what, how far, time so far and the time left."""
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("eta"), TimeRemainingColumn(), console=console, transient=True, disable=quiet)


def _with_progress(name: str, quiet: bool, work: Callable[[ProgressCallback], RunResult]) -> RunResult:
    """Run `work(progress)` under a progress bar labelled `name`; Ctrl-C stops it at its next
    report."""
    with _progress_bar(quiet) as bar, _ctrl_c_at_reports() as check:
        task = bar.add_task(f"{escape(name)}: stops", total=None)

        def report(stage: str, done: int, total: int) -> None:
            check()
            bar.update(task, description=f"{escape(name)}: {stage}", completed=done, total=total)

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


def _rerun_help(default_file: str) -> str:
    return (f"rerun viewer: 'spawn', 'save' ({default_file} in the results folder), 'save:FILE.rrd', "
            "'serve' (gRPC + web viewer), 'connect:URL' (a running viewer, e.g. rerun+http://host:9876/proxy)")


def _rerun_target(text: str, memory_limit: str):
    """Parse --rerun; bad values are usage errors. `save` alone leaves the path to the caller."""
    from .viz.rerun_sink import RerunTarget

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


def _summary_table(result: RunResult) -> Table:
    """One row per configuration; narrow enough for an 80-column terminal."""
    from rich import box

    held = any(c.holdout is not None for c in result.configurations.values())
    table = Table(title=f"{escape(result.name)} (seed {result.seed}, {len(result.traverse.stops)} stops)",
                  box=box.SIMPLE_HEAD, padding=(0, 1), caption="m: metres against the reference; GPS m: average "
                  "error against the fixes in the graph; held m: RMS 2-D to the held-out fixes")
    table.add_column("config", justify="left", no_wrap=True)
    columns = ["avg m", "clos. %", "ATE m", "length", "bridged", "GPS m"] + (["held m"] if held else [])
    for col in columns:
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


def _parse_configs(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise ConfigError("--configs: give one or more configuration names or kinds joined by '+', "
                          "separated by commas (e.g. vo,vo+gps)")
    return names


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
    from .pipeline import select_configurations
    from .results import RunOptions
    from .sources import SourceOptions

    if resume is not None:
        given = {"SOURCE": source, "--out": out, "--seed": seed, "--configs": configs, "--batch": batch or None,
                 "--gps-topic": gps_topic, "--odom-topic": odom_topic, "--holdout-every": holdout_every,
                 "--geoid-height": geoid_height, "--detector": detector, "--stereo-topics": stereo_topics,
                 "--skip-bad-frames": skip_bad_frames or None}
        try:
            clash = [name for name, value in given.items() if value is not None]
            if clash:
                raise ConfigError(f"--resume goes on with the run's own source and options; drop {', '.join(clash)}")
            target = _rerun_target(rerun, viewer_memory) if rerun is not None else None
            partial, out = _partial_and_out(resume)
            from .io.checkpoint import read_checkpoint

            inputs, states = read_checkpoint(partial)
        except PancamGraphError as exc:
            raise _fail(exc, bad_input=True) from None
        n = len(inputs.data.traverse.stops)
        where = (f"at stop {states[0].next_stop}" if len(states) == 1 else "with its groups of configurations at "
                 + ", ".join(f"stop {s.next_stop} ({', '.join(s.localizers)})" for s in states))
        console.print(f"resuming {inputs.data.traverse.name} {where} of {n} (from {partial})")
        options = dataclasses.replace(inputs.options, processes=1 if one_process else inputs.options.processes)
        _start_process_server(options)
        _run_source(inputs.data, options, out, target, quiet, checkpoint_every, not no_plots, resume=states)
        return
    source = source or "denver_trail"
    try:
        options = RunOptions(seed=seed, configs=_parse_configs(configs), batch=batch,
                             processes=1 if one_process else cores())
        _start_process_server(options)
        target = _rerun_target(rerun, viewer_memory) if rerun is not None else None
        _check_out(out)
        data = _open_with_progress(source, SourceOptions(seed, gps_topic, odom_topic, holdout_every, geoid_height,
                                                         _detector(detector), skip_bad_frames or None,
                                                         _topics(stereo_topics)), quiet)
        select_configurations(data.estimator, data.traverse, options.configs)  # before anything is written
    except FrameError as exc:
        raise _keep_frontend_work(exc, out) from None
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
    for reason in data.rejected[:10]:
        console.print(Text("fix left out: ", style="yellow") + Text(reason))
    if len(data.rejected) > 10:
        console.print(Text(f"... {len(data.rejected) - 10} more fixes left out", style="yellow"))
    _run_source(data, options, out, target, quiet, checkpoint_every, not no_plots)


def _partial_and_out(resume: Path) -> tuple[Path, Path]:
    """(the killed run's staging folder, the results folder it was to become) from --resume,
    which may name either."""
    resume = Path(resume)
    if resume.name.endswith(".partial"):
        return resume, resume.with_name(resume.name.removesuffix(".partial"))
    partial = resume.with_name(resume.name + ".partial")
    if partial.is_dir():
        return partial, resume
    raise ConfigError(f"--resume {resume}: expected a killed run's <out>.partial folder")


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


def _open_with_progress(source: str, options, quiet: bool) -> SourceData:
    """Read a source; an image source runs the front-end over every frame under a progress bar."""
    from .sources import open_source

    name = Path(source).name or source
    return _with_progress(name, quiet, lambda report: open_source(source, options, report))


def _keep_frontend_work(exc: FrameError, out: Path | None) -> typer.Exit:
    """A bad frame stopped the front-end: what it tracked before is written as an observation
    folder (in <out>.partial, like any failed run's work) so it is not lost."""
    from .io.observations import write_observations
    from .io.results import results_folder

    data = exc.partial
    if data is None:
        return _fail(exc, bad_input=True)
    out = out or Path("results") / f"{data.traverse.name}-{datetime.now():%Y%m%d-%H%M%S}"
    kept = out.with_name(out.name + ".partial") / "observations"
    try:
        with results_folder(out) as folder:
            write_observations(folder / "observations", data.traverse, data.estimator, data.seed, data.truth)
            raise exc  # leaving as a failed run keeps the folder as <out>.partial
    except FrameError:
        pass
    except PancamGraphError as write_error:
        console.print(Text("error: ", style="bold red") + Text(f"cannot keep the front-end's work: {write_error}"))
        return _fail(exc, bad_input=True)
    n = len(data.traverse.stops)
    console.print(Text("error: ", style="bold red") + Text(
        f"{exc}\nthe front-end's observations of stops 0-{n - 1} are kept in {kept} (`pancam-graph run {kept}` "
        "runs the back-end on them); --skip-bad-frames leaves a bad stop to the VO bridge instead"), soft_wrap=True)
    return typer.Exit(EXIT_USAGE)


def _check_out(out: Path | None) -> None:
    """Results are never written over: --out must be new or an empty folder."""
    if out is None or not out.exists():
        return
    if not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a folder")
    if any(out.iterdir()):
        raise ConfigError(f"--out {out}: folder exists and is not empty; choose another --out")


def _run_source(data: SourceData, options: RunOptions, out: Path | None, target, quiet: bool,
                checkpoint_every: float, figures: bool = True, resume: list[RunState] | None = None) -> None:
    """Run the back-end into a results folder; with `resume`, go on from that saved state in the
    killed run's own staging folder."""
    from .io.checkpoint import CheckpointWriter, RunInputs, remove_checkpoint
    from .io.results import results_folder, write_run
    from .pipeline import run_traverse
    from .viz.report import write_report

    label = f"seed{data.seed}-" if data.scenario is not None else ""
    out = out or Path("results") / f"{data.traverse.name}-{label}{datetime.now():%Y%m%d-%H%M%S}"
    recording = folder = checkpoints = None
    try:
        with results_folder(out, resume=resume is not None) as folder:
            checkpoints = CheckpointWriter(folder, RunInputs(data, options), checkpoint_every,
                                           resumed=bool(resume))
            listener = None
            if target is not None:
                from dataclasses import replace

                from .viz.rerun_live import RerunRecorder
                from .viz.rerun_sink import open_recording

                if target.mode == "save" and target.path is None:
                    target = replace(target, path=folder / "recording.rrd")
                try:
                    recording = open_recording(target, f"{data.traverse.name} seed {data.seed}")
                    listener = RerunRecorder(recording.stream)
                except ViewerUnavailable as exc:  # the results are the product, the viewer is not
                    console.print(Text("warning: ", style="bold yellow") + Text(f"{exc}; running without it"))
            try:
                result = _with_progress(data.traverse.name, quiet, lambda report: run_traverse(
                    data.traverse, data.truth, data.estimator, data.seed, options, report, listener,
                    source=data.info, scenario=data.scenario, held_out=data.held_out, save=checkpoints,
                    resume=resume, vo_motions=data.vo_motions))
                write_run(result, folder)
                report = write_report(result, folder, figures)
                remove_checkpoint(folder)
            finally:
                if recording is not None:  # also on failure: keep what was recorded
                    recording.close()
    except PancamGraphError as exc:
        raise _fail(exc) from None
    except KeyboardInterrupt:
        partial = out.with_name(out.name + ".partial")
        saved = checkpoints.saved_stops if checkpoints is not None else []
        goes_on = (f"`pancam-graph run --resume {partial}` goes on from stop {min(saved)}" if saved
                   else "no checkpoint was saved yet")
        _interrupted(f"what was done is in {partial}; {goes_on}")
    import sys

    Console(width=80).print(_summary_table(result))
    sys.stdout.flush()
    for name, reason in result.skipped.items():
        console.print(Text(f"not run: {name} ({reason})", style="dim"))
    saved = f" ({checkpoints.saves} checkpoints saved in {checkpoints.save_s:.1f} s)" if checkpoints.saves else ""
    console.print(f"wall {result.wall_s:.1f} s{saved}; results in {out} (report: {out / report.name})")
    if recording is not None and recording.target.mode == "save":
        path = recording.target.path
        shown = out / path.name if path.parent == folder else path
        console.print(f"rerun recording: {shown} (open with `rerun {shown}` or `pancam-graph view {out}`)")
    if recording is not None and recording.target.mode == "serve":
        _serve_until_interrupted(recording.served_url)


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
    from .io.observations import write_observations
    from .sources import SourceOptions, source_kind

    try:
        _check_out(out)
        if source_kind(source) not in ("kitti_odometry", "image_folder"):
            raise ConfigError(f"{source}: track needs stereo images (an image folder or a KITTI odometry "
                              "sequence folder)")
        data = _open_with_progress(source, SourceOptions(detector=_detector(detector),
                                                         skip_bad_frames=skip_bad_frames or None), quiet)
        write_observations(out, data.traverse, data.estimator, data.seed, data.truth)
    except FrameError as exc:
        raise _keep_frontend_work(exc, out) from None
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
    frames = [len(s.stereo) for s in data.traverse.stops]
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
    try:
        _check_out(out)
        sc = _load(scenario)
        start = time.perf_counter()
        if control_field:
            from .render.control_field import render_control_field

            n = _with_progress(sc.name, quiet, lambda report: render_control_field(sc, out, views, seed, report))
        else:
            from .render.images import render_scenario

            n = _with_progress(sc.name, quiet, lambda report: render_scenario(sc, out, seed, report))
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
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
    from .io.calibration import read_opencv_yaml, write_opencv_yaml
    from .io.calibration_images import TRUTH_FILE, calibrate_folder

    try:
        if out.exists() and out.is_dir():
            raise ConfigError(f"--out {out}: is a folder; give the YAML file to write")
        truth = truth or (folder / TRUTH_FILE if (folder / TRUTH_FILE).is_file() else None)
        reference = read_opencv_yaml(truth) if truth is not None else None
        fit = _with_progress(folder.name, quiet, lambda report: calibrate_folder(folder, field, report))
        out.parent.mkdir(parents=True, exist_ok=True)
        write_opencv_yaml(out, fit.calibration, rectification=True)
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
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

    try:
        print(dump_scenario(_load(scenario)), end="")
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None


@app.command("view")
def view_command(
    results: Path = typer.Argument(..., help="a results folder written by `pancam-graph run`"),
    rerun: str = typer.Option("spawn", "--rerun", help=_rerun_help("replay.rrd")),
    viewer_memory: str = typer.Option("25%", "--viewer-memory", help="memory limit of a spawned or served viewer"),
) -> None:
    """Replay a finished results folder into rerun with the live run's layout."""
    from dataclasses import replace

    from .io.results import read_run
    from .viz.rerun_replay import replay
    from .viz.rerun_sink import open_recording

    try:
        target = _rerun_target(rerun, viewer_memory)
        if target.mode == "save" and target.path is None:
            target = replace(target, path=results / "replay.rrd")
        try:
            saved = read_run(results)
        except PancamGraphError as exc:  # the folder given is the input: a usage error
            raise _fail(exc, bad_input=True) from None
        recording = open_recording(target, f"{saved.name} (replay of {results.name})")
        replay(saved, recording.stream)
        recording.close()
    except PancamGraphError as exc:
        raise _fail(exc) from None
    if target.mode == "save":
        console.print(f"rerun recording: {target.path}")
    elif target.mode == "serve":
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
    from .evaluation.evaluate import evaluate_trajectories
    from .geodesy import LocalFrame
    from .io.results import read_local_frame, write_json
    from .io.trajectories import read_trajectory

    try:
        if align not in ("none", "se3", "yaw"):
            raise ConfigError(f"--align {align!r}: expected none, se3 or yaw")
        frame = None
        if origin is not None:
            try:
                frame = LocalFrame(*(float(v) for v in origin.split(",")))
            except (TypeError, ValueError):
                raise ConfigError(f"--origin {origin!r}: expected LAT,LON,H in degrees and metres") from None
        frame = frame or read_local_frame(estimate.parent)
        est = read_trajectory(estimate, frame, gps_sigma)
        ref = read_trajectory(reference, frame, gps_sigma)
        if (est.geodetic is None) != (ref.geodetic is None) and frame is None:
            raise ConfigError(f"{reference if ref.geodetic is not None else estimate}: a GPS log needs the ENU "
                              "origin of the other trajectory: give --origin LAT,LON,H")
        result = evaluate_trajectories(est, ref, align, max_dt, rpe_delta)
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
    m = result.metrics
    document = {**result.as_dict(), "configs": {estimate.stem: m.as_dict()}}
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
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "metrics.json", document)
        from .viz.plots import evaluation_plot

        evaluation_plot(result, out / "eval.png")
        console.print(f"metrics in {out / 'metrics.json'}, plot {out / 'eval.png'}")
    else:
        print(json.dumps(document, indent=2))


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

    try:
        sweep = load_spec(spec)
        runs = plan(sweep, out, spec.parent)
        (out / "sweep.toml").write_text(spec.read_text(encoding="utf-8"), encoding="utf-8")
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
    start = time.perf_counter()
    with _progress_bar(quiet) as bar:
        task = bar.add_task(f"{escape(spec.stem)}: runs", total=len(runs))

        def report(record, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)
            if record.status in ("failed", "timeout"):
                bar.console.print(Text(f"{record.run.name}: {record.status}: {record.message}", style="yellow"))

        try:
            records = run_sweep(runs, sweep.timeout_s, workers, scheduler, report)
        except PancamGraphError as exc:
            raise _fail(exc) from None
    try:
        rows = run_rows(records)
        summary = summarize(rows)
        write_tables(out, records, rows, summary)
    except PancamGraphError as exc:
        raise _fail(exc) from None
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
    import numpy as np

    from .pipeline import run
    from .results import RunOptions, cost_along, memory_along, percentiles

    if scenario == "frontend":
        _bench_frontend(source, detector)
        return
    if scenario == "sites":
        _bench_sites(source)
        return
    if source is not None or detector is not None:
        raise _fail(ConfigError("SOURCE and --detector go with 'bench frontend' only"), bad_input=True)
    if monte_carlo:
        seeds = max(seeds, monte_carlo)
        if workers:
            _bench_monte_carlo_sweep(scenario, seed, seeds, workers)
            return
    load_before = os.getloadavg()
    try:
        sc = _load(scenario)
        first = sc.seed if seed is None else seed
        results, walls, recorded_walls = [], [], []
        options = RunOptions(processes=cores())
        _start_process_server(options)
        for s in range(first, first + seeds):
            start = time.perf_counter()
            results.append(run(sc, dataclasses.replace(options, seed=s)))
            walls.append(time.perf_counter() - start)
            if rerun:
                recorded_walls.append(_time_recorded_run(sc, s))
            if seeds > 1 or rerun:
                extra = f", with --rerun save {recorded_walls[-1]:.1f} s" if rerun else ""
                console.print(f"seed {s}: {walls[-1]:.1f} s{extra}")
    except PancamGraphError as exc:
        raise _fail(exc) from None
    ms = np.concatenate([r.update_ms for r in results])
    report = {
        "scenario": sc.name,
        "seeds": [r.seed for r in results],
        "stops": [len(r.traverse.stops) for r in results],
        "isam2_update_ms": {**percentiles(ms), "count": int(len(ms))},
        "isam2_update_ms_per_config": {
            n: percentiles(np.concatenate([r.configurations[n].update_ms for r in results]))
            for n in results[0].configurations
        },
        "vo_s": float(np.mean([r.vo_s for r in results])),
        "wall_s": float(np.mean(walls)),
        "peak_memory_mb": _peak_memory(results[0]),
        # the first seed's groups of configurations and how long each took in its process
        "groups": [{"label": p.label, "configurations": list(p.configurations), "seconds": round(p.seconds, 2),
                    "cpu_seconds": round(p.cpu_seconds, 2)} for p in results[0].processes],
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
    }
    # the first seed's cost along the path: flat, or growing with the traverse?
    report["isam2_update_ms_per_km"] = cost_along(results[0], 1000.0)
    distance = results[0].reference_distance()
    report["peak_rss_mb_along_path"] = [{"at_m": round(float(distance[k]), 1), "peak_rss_mb": round(mb, 1)}
                                        for k, mb in memory_along(results[0])]
    if plot is not None:
        from .viz.plots import plot_cost_along

        try:
            plot_cost_along(report["isam2_update_ms_per_km"], report["peak_rss_mb_along_path"],
                            f"{sc.name} seed {first}", plot)
        except OSError as exc:
            raise _fail(ResultsError(f"--plot {plot}: cannot write it: {exc.strerror}")) from None
        report["plot"] = str(plot)
    if rerun:
        ratios = np.array(recorded_walls) / np.array(walls)
        report["rerun_save"] = {
            "wall_s": float(np.mean(recorded_walls)),
            "overhead_pct": 100.0 * (float(np.sum(recorded_walls)) / float(np.sum(walls)) - 1.0),
            "overhead_pct_median_pair": 100.0 * (float(np.median(ratios)) - 1.0),
            "note": "total wall with a RerunRecorder saving to a temporary .rrd vs without; each seed run "
                    "both ways back to back",
        }
    if seeds > 1:
        report["over_seeds"] = {
            n: {
                stat: {"mean": float(np.mean(v)), "std": float(np.std(v)), "max": float(np.max(v))}
                for stat, v in (
                    ("relative_closure_pct", [r.configurations[n].metrics.relative_closure_pct for r in results]),
                    ("ate_rmse_m", [r.configurations[n].metrics.ate_rmse_m for r in results]),
                    ("bridged_stops", [r.configurations[n].bridged_stops for r in results]),
                )
            }
            for n in results[0].configurations
        }
    if monte_carlo:
        from .evaluation.consistency import monte_carlo_summary

        report["monte_carlo"] = {n: monte_carlo_summary([r.configurations[n].consistency for r in results])
                                 for n in results[0].configurations
                                 if all(r.configurations[n].consistency is not None for r in results)}
    print(json.dumps(report, indent=2))


def _peak_memory(result) -> dict[str, dict[str, float]]:
    """Peak memory (MB): the most the run's processes held at once (sampled), and each
    process's own peak and their sum: this one, and those that ran groups of configurations
    side by side. Resident set size counts the pages the workers share (the fork server's
    imports) in each; the proportional set size (sampled at checkpoints) counts each its share."""
    from .group import pss_mb

    rss = {"this process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    pss = {"this process": pss_mb() or 0.0}
    for process in result.processes:
        if process.memory_mb and process.pid != os.getpid():
            label = f"process {process.pid}"
            rss[label] = max(rss.get(label, 0.0), max(mb for _, mb in process.memory_mb))
            pss[label] = max(pss.get(label, 0.0), process.peak_pss_mb or 0.0)
    return {"at_once": round(result.peak_memory_mb, 1) if result.peak_memory_mb is not None else None,
            "rss": {**{k: round(v, 1) for k, v in rss.items()}, "sum": round(sum(rss.values()), 1)},
            "pss": {**{k: round(v, 1) for k, v in pss.items()}, "sum": round(sum(pss.values()), 1)}}


def _bench_monte_carlo_sweep(scenario: str, seed: int | None, seeds: int, workers: int) -> None:
    """bench --monte-carlo as a sweep: the same summary, the runs on a local Dask cluster."""
    import tempfile

    import numpy as np

    from .config import resolve_scenario
    from .sweep.runner import run_sweep
    from .sweep.spec import SweepSpec, plan
    from .sweep.table import monte_carlo, run_rows

    try:
        sc = _load(scenario)
        first = sc.seed if seed is None else seed
        spec = SweepSpec(scenarios=[str(resolve_scenario(scenario).resolve())], seeds=seeds, first_seed=first)
        start = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="pancam-graph-bench-") as folder:
            records = run_sweep(plan(spec, Path(folder)), spec.timeout_s, workers)
            failed = [r for r in records if r.status != "done"]
            if failed:
                raise ResultsError(f"{len(failed)} of {len(records)} runs failed; first: {failed[0].run.name}: "
                                   f"{failed[0].message}")
            rows = run_rows(records)
    except PancamGraphError as exc:
        raise _fail(exc) from None
    configs = dict.fromkeys(row["config"] for row in rows)
    report = {"scenario": sc.name, "seeds": list(range(first, first + seeds)), "workers": workers,
              "wall_s": time.perf_counter() - start,
              "monte_carlo": {c: mc for c in configs if (mc := monte_carlo([r for r in rows if r["config"] == c]))}}
    report["over_seeds"] = {
        c: {stat: {"mean": float(np.mean(v)), "max": float(np.max(v))}
            for stat in ("relative_closure_pct", "ate_rmse_m")
            if (v := [r[stat] for r in rows if r["config"] == c and r.get(stat) is not None])}
        for c in configs}
    print(json.dumps(report, indent=2))


def _bench_sites(source: str | None, compared_sites: int = 3) -> None:
    """The site panoramas of an image folder: pan/tilt-aided against unaided (SIFT) matching of
    overlapping frames on the first `compared_sites` sites (SIFT takes about 25 s a site), and
    the tie points between every pair of sites; each checked against the renderer's truth when
    the folder names a bundled scenario."""
    import os

    import numpy as np

    from .config import FrontendConfig, bundled_scenarios
    from .frontend.motion import VoMotions
    from .frontend.panorama import PanoramaMatcher, PanoramaView, unaided_matches
    from .io.observations import is_image_folder, read_observations
    from .render.truth import RenderedTruth
    from .sources import image_folder
    from .sources.site_images import images_by_stop, with_site_panoramas

    if source is None or not is_image_folder(Path(source)):
        raise _fail(ConfigError(f"bench sites {source or ''}: give an image folder with site panoramas "
                                "(pancam-graph render SCENARIO --out FOLDER writes one)"), bad_input=True)
    load_before = os.getloadavg()
    try:
        obs = read_observations(Path(source))
        scenario = bundled_scenarios().get(obs.traverse.name)
        truth = None if scenario is None or obs.truth is None else RenderedTruth(
            _load(str(scenario)), obs.seed, obs.truth.world_T_body, obs.traverse.rig.wac)
        pairs = image_folder.FramePairs(obs)
        with _progress_bar() as bar:
            task = bar.add_task("front-end", total=len(obs.traverse.stops))
            tracked = image_folder.load(Path(source), FrontendConfig(), sites=False,
                                        progress=lambda _, done, total: bar.update(task, completed=done, total=total))
        vo = VoMotions.estimate(tracked.traverse, tracked.estimator)
        with _progress_bar() as bar:
            task = bar.add_task("site panoramas", total=None)
            _, report = with_site_panoramas(obs, list(tracked.traverse.stops), pairs.read_view, vo, FrontendConfig(),
                                            progress=lambda _, done, total: bar.update(task, completed=done,
                                                                                       total=total),
                                            read_hrc=pairs.read_hrc if obs.traverse.rig.hrc is not None else None)
        # aided against unaided matching of overlapping frames, on the first sites
        rig = obs.traverse.rig
        matcher = PanoramaMatcher(rig.wac, rig.baseline_m)
        aided = {"frame_pairs": 0, "links": 0, "seconds": 0.0, "errors": []}
        unaided = {"frame_pairs": 0, "matches": 0, "seconds": 0.0, "errors": []}
        by_stop = images_by_stop(obs)
        for stop in list(by_stop)[:compared_sites]:
            views = [PanoramaView(im.pan_rad, im.tilt_rad, rig.body_T_left(im.pan_rad, im.tilt_rad).matrix(),
                                  *pairs.read_view(im)) for im in by_stop[stop]]
            matcher(stop, 0, views)
            for i, a in enumerate(views):
                for b in views[i + 1:]:
                    start = time.perf_counter()
                    links = matcher.overlap_matches(a, b)
                    aided["seconds"] += time.perf_counter() - start
                    if not links:
                        continue
                    aided["frame_pairs"] += 1
                    aided["links"] += len(links)
                    start = time.perf_counter()
                    ua, ub = unaided_matches(a, b)
                    unaided["seconds"] += time.perf_counter() - start
                    unaided["frame_pairs"] += 1
                    unaided["matches"] += len(ua)
                    if truth is None:
                        continue
                    uv_a = dict(zip(a.observations.track_ids.tolist(), a.observations.uvv[:, [0, 2]], strict=True))
                    uv_b = dict(zip(b.observations.track_ids.tolist(), b.observations.uvv[:, [0, 2]], strict=True))
                    aided["errors"] += [truth.transfer_error((stop, a.body_T_camera, uv_a[ta]),
                                                             (stop, b.body_T_camera, uv_b[tb])) for ta, tb in links]
                    unaided["errors"] += [truth.transfer_error((stop, a.body_T_camera, pa), (stop, b.body_T_camera, pb))
                                          for pa, pb in zip(ua, ub, strict=True)]
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None

    def scored(errors: list[float], within_px: float) -> dict:
        e = np.asarray(errors)
        if not len(e):
            return {}
        return {f"correct_within_{within_px:g}px_pct": round(100.0 * float(np.mean(e < within_px)), 2),
                "median_error_px": round(float(np.median(e)), 3)}

    site = {s.stop: s for s in report.sites}
    pair_rows, tie_errors = [], []
    for pair in report.pairs:
        errors = [] if truth is None else [truth.transfer_error(
            (pair.a_stop, site[pair.a_stop].views[t.a_view].body_T_camera, t.a_uvv[[0, 2]]),
            (pair.b_stop, site[pair.b_stop].views[t.b_view].body_T_camera, t.b_uvv[[0, 2]]))
            for t in pair.result.ties]
        tie_errors += errors
        pair_rows.append({"a_stop": pair.a_stop, "b_stop": pair.b_stop, "distance_m": round(pair.distance_m, 1),
                          "adjacent": pair.b_stop == report.next_site(pair.a_stop),
                          "candidates": pair.result.candidates, "matched": len(pair.result.matches),
                          "verified": len(pair.result.ties), "seconds": round(pair.result.seconds, 2),
                          "note": pair.result.note, **scored(errors, 3.0)})
    adjacent = [r["verified"] for r in pair_rows if r["adjacent"]]
    hrc_rows, hrc_errors = [], []
    for stop, frames in report.hrc.items():
        for m in frames:
            body_T_hrc = rig.body_T_hrc(m.pan_rad, m.tilt_rad).matrix()
            errors = [] if truth is None else [
                truth.transfer_error((stop, site[stop].views[v].body_T_camera, wac_uv), (stop, body_T_hrc, uv), rig.hrc)
                for v, wac_uv, uv in zip(m.wac_view, m.wac_uv, m.uv, strict=True)]
            hrc_errors += errors
            hrc_rows.append({"stop": stop, "pan_deg": round(float(np.rad2deg(m.pan_rad)), 1),
                             "predicted": m.predicted, "matched": len(m.track_ids),
                             "dropped_for_shift": m.disagreeing,
                             "shift_hrc_px": [round(float(x), 1) for x in m.shift_px],
                             "correct_within_7px": int(np.sum(np.array(errors) < 7.0)) if truth is not None else None,
                             "seconds": round(m.seconds, 3)})
    print(json.dumps({
        "source": source, "sites": len(report.sites), "summary": report.summary(),
        "truth": "renderer depth at the true poses" if truth is not None else None,
        "ties": {"total": sum(len(p.result.ties) for p in report.pairs),
                 "adjacent_pairs_fewest": min(adjacent) if adjacent else 0,
                 "adjacent_pairs_median": float(np.median(adjacent)) if adjacent else 0.0,
                 **scored(tie_errors, 3.0), **scored(tie_errors, 2.0), "pairs": pair_rows},
        "hrc": {
            "frames": len(hrc_rows),
            "matched_median": float(np.median([r["matched"] for r in hrc_rows])) if hrc_rows else 0.0,
            "matched_fewest": min((r["matched"] for r in hrc_rows), default=0),
            "correct_fewest": min((r["correct_within_7px"] or 0 for r in hrc_rows), default=0),
            **scored(hrc_errors, 7.0), **scored(hrc_errors, 3.0),
            "note": "HRC pixels against where the WAC feature's terrain point is in the HRC image; 7 HRC px is "
                    "one WAC pixel",
            "frames_detail": hrc_rows,
        },
        "overlapping_frames": {
            "sites": min(compared_sites, len(by_stop)),
            "pan_tilt_aided": {k: v for k, v in aided.items() if k != "errors"} | scored(aided["errors"], 2.0),
            "unaided_sift": {k: v for k, v in unaided.items() if k != "errors"} | scored(unaided["errors"], 2.0),
            "note": "aided: seconds of back-projection, warping and optical flow over every frame pair (the "
                    "stereo features are the site's own); unaided: SIFT detection and matching of the left "
                    "images and a RANSAC fundamental matrix, on the frame pairs the aided matching found "
                    "overlapping",
        },
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
    }, indent=2))


def _bench_frontend(source: str | None, detector: str | None) -> None:
    import os

    import numpy as np

    from .config import FrontendConfig
    from .frontend.tracker import StereoTracker
    from .sources import source_kind
    from .sources.frames import frame_ms, track_frames

    try:
        kind = source_kind(source) if source is not None else None
        if kind not in ("kitti_odometry", "image_folder"):
            raise ConfigError(f"bench frontend {source or ''}: give stereo images (an image folder or a KITTI "
                              "odometry sequence folder, e.g. ../shared/data/real/kitti_odometry_51)")
        config = FrontendConfig(detector=_detector(detector) or "gftt")
        stops, read_raw, size, rectify, camera_motion = _stereo_frames(Path(source), kind)
        tracker = StereoTracker(config)
        read_ms: list[float] = []

        def read_pair(k: int):
            start = time.perf_counter()
            pair = read_raw(k)
            read_ms.append((time.perf_counter() - start) * 1e3)
            return pair if rectify is None else rectify(pair, tracker.times)

        load_before = os.getloadavg()
        with _progress_bar() as bar:
            task = bar.add_task("front-end", total=len(stops))
            # the run's own loop over the frames, so the bench times what `run` does
            tracked = track_frames(stops, read_pair, tracker, lambda tracked, notes: tracked,
                                   progress=lambda _, done, total: bar.update(task, completed=done),
                                   camera_motion=camera_motion if config.odometry_aided else None)
    except PancamGraphError as exc:
        raise _fail(exc, bad_input=True) from None
    frame = frame_ms(tracker)
    features = [len(s.stereo) for s in tracked]
    stages = tracker.times.summary()
    stages.pop("frame")
    print(json.dumps({
        "source": source, "detector": config.detector, "frames": len(tracked), "image_size": [size[1], size[0]],
        "frame_ms": {"median": float(np.median(frame)), "p95": float(np.percentile(frame, 95)),
                     "mean": float(frame.mean())},
        "stages_ms": stages, "image_read_ms_median": float(np.median(read_ms)),
        "features_per_frame_median": float(np.median(features)),
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
        "note": "frame_ms: images in memory -> rectified (raw images) -> observations (reading the images "
                "not included); gftt: corner detection runs beside temporal tracking, whose time includes "
                "the overlap, and detect is what is left of it",
    }, indent=2))


def _stereo_frames(folder: Path, kind: str):
    """(the stops, a reader of stop k's raw pair, (height, width), the rectification or None,
    the camera's motion from dead reckoning or None) of an image source."""
    if kind == "kitti_odometry":
        from .io.kitti import read_kitti_odometry
        from .records import StereoObservations, Stop

        sequence = read_kitti_odometry(folder)
        cam = sequence.stereo.camera
        stops = [Stop(k, float(sequence.times_s[k]), StereoObservations.empty()) for k in range(len(sequence))]
        return stops, sequence.stereo_pair, (cam.height, cam.width), None, None
    from .io.observations import read_observations
    from .sources.image_folder import FramePairs, odometry_camera_motion

    obs = read_observations(folder)
    pairs = FramePairs(obs)
    rectify = None if pairs.rectify is None else pairs.rectified
    return obs.traverse.stops, pairs.read, pairs.size, rectify, odometry_camera_motion(obs.traverse)


def _time_recorded_run(scenario, seed: int) -> float:
    import tempfile

    from .pipeline import run
    from .results import RunOptions
    from .viz.rerun_live import RerunRecorder
    from .viz.rerun_sink import RerunTarget, open_recording

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        recording = open_recording(RerunTarget("save", path=Path(tmp) / "bench.rrd"), "bench")
        run(scenario, RunOptions(seed=seed), listener=RerunRecorder(recording.stream))
        recording.close()
        return time.perf_counter() - start


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
    from .analysis.report import SEED_TABLE_3_2, analyze
    from .rig import RIG_PRESETS
    from .viz.analysis_plots import write_analysis

    try:
        _check_out(out)
    except ConfigError as exc:
        raise _fail(exc) from None
    custom = [baseline, focal_px, fov_deg]
    if any(v is not None for v in custom) and not all(v is not None for v in custom):
        raise _fail(ConfigError("a custom rig needs --baseline, --focal-px and --fov together"))
    try:
        if all(v is not None for v in custom):
            rigs = [AnalysisRig("custom", baseline, focal_px, fov_deg)]
        else:
            rigs = [AnalysisRig.preset(name) for name in (rig or list(RIG_PRESETS))]
    except ValueError as exc:
        raise _fail(ConfigError(f"--rig: {exc}")) from None
    assumptions = Assumptions(sigma_px=sigma_px)
    start = time.perf_counter()
    with _progress_bar() as bar:
        task = bar.add_task("analysing rigs", total=len(rigs))
        rows = analyze(rigs, assumptions, progress=lambda done, total: bar.update(task, completed=done))
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
    from .io.observations import write_observations
    from .sim import simulate

    try:
        sc = _load(scenario)
        _check_out(out)
        seed_used = sc.seed if seed is None else seed
        with console.status(f"simulating {escape(sc.name)} (seed {seed_used})"):
            traverse, truth = simulate(sc, seed_used)
            write_observations(out, traverse, sc.estimator, seed_used, None if no_truth else truth, sc.rig)
    except PancamGraphError as exc:
        raise _fail(exc) from None
    console.print(f"{len(traverse.stops)} stops written to {out}")


@app.command("scenarios")
def scenarios_command() -> None:
    """List the bundled scenarios."""
    from .config import bundled_scenarios, load_scenario

    for name, path in sorted(bundled_scenarios().items()):
        try:
            description = load_scenario(path).description
        except ConfigError as exc:
            description = f"(invalid: {exc})"
        print(f"{name:16s} {description}")


_interrupt_reported = False


def _interrupted(what: str) -> NoReturn:
    """Ctrl-C in a command that has something to say about it (exit 130)."""
    global _interrupt_reported
    console.print(Text("interrupted: ", style="bold red") + Text(what), soft_wrap=True)
    _interrupt_reported = True
    raise SystemExit(EXIT_INTERRUPTED)


def main() -> None:
    """The console script: the one place that turns what escapes a command into an exit code."""
    try:
        app()
    except KeyboardInterrupt:
        console.print(Text("interrupted", style="bold red"))
        raise SystemExit(EXIT_INTERRUPTED) from None
    except SystemExit as exc:  # typer turns Ctrl-C into a silent exit 130
        if exc.code == EXIT_INTERRUPTED and not _interrupt_reported:
            console.print(Text("interrupted", style="bold red"))
        raise
    except PancamGraphError as exc:  # a command that forgot to catch its own
        console.print(Text("error: ", style="bold red") + Text(str(exc)))
        raise SystemExit(EXIT_USAGE if isinstance(exc, _USAGE_ERRORS) else EXIT_FAILURE) from None
    except OSError as exc:  # a full disk, a permission: one line, not a traceback
        console.print(Text("error: ", style="bold red") + Text(f"{exc.filename or ''}: {exc.strerror or exc}"))
        raise SystemExit(EXIT_FAILURE) from None


if __name__ == "__main__":
    main()
