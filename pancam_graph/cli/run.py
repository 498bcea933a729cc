"""`pancam-graph run`: a source through every configuration into a results folder, or a killed
run resumed; the summary table."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from ..config import SourceOptions
from ..errors import ConfigError
from .app import app, console, leave_without_rerun, user_input
from .common import (
    SERVE_FOR_HELP,
    announce_viewer,
    examples,
    parse_configs,
    rerun_help,
    rerun_target,
    serve_until_interrupted,
    with_progress,
    with_source_options,
)

if TYPE_CHECKING:  # the heavy imports wait until a command needs them: --help stays fast
    from ..api import RunOutcome


def _summary_table(outcome: RunOutcome) -> Table:
    """One row per configuration; narrow enough for an 80-column terminal."""
    from rich import box

    result = outcome.result
    held = any(c.holdout is not None for c in result.configurations.values())
    table = Table(title=f"{escape(result.title)} ({len(result.traverse.stops)} stops)",
                  box=box.SIMPLE_HEAD, padding=(0, 1), caption="m: metres against the reference; ATE: unaligned "
                  "(the start prior's frame), se3: SE(3)-aligned; GPS m: average error against the fixes in the graph"
                  + ("; held m: RMS 2-D to the held-out fixes" if held else ""))
    table.add_column("config", justify="left", no_wrap=True)
    for col in ["clos. %", "ATE m", "se3 m", "length", "bridged", "GPS m"] + (["held m"] if held else []):
        table.add_column(col, justify="right")
    for name, c in result.configurations.items():
        m, vs = c.metrics, c.metrics_vs_gps
        cells = ["-"] * 4 if m is None else [f"{m.relative_closure_pct:.3f}", f"{m.ate_unaligned_rmse_m:.2f}",
                                             f"{m.ate_se3_rmse_m:.2f}", f"{m.length_ratio:.4f}"]
        row = [name, *cells, str(c.bridged_stops), "-" if vs is None else f"{vs.average_error_m:.2f}"]
        if held:
            row.append("-" if c.holdout is None else f"{c.holdout.rms_2d_m:.3f}")
        table.add_row(*row)
    return table


def _print_outcome(outcome: RunOutcome, serve_for_s: float | None) -> None:
    for warning in outcome.warnings:
        console.print(Text("warning: ", style="bold yellow") + Text(warning), soft_wrap=True)
    Console(width=80).print(_summary_table(outcome))
    sys.stdout.flush()
    for name, reason in outcome.result.skipped.items():
        console.print(Text(f"not run: {name} ({reason})", style="dim"), soft_wrap=True)
    saved = (f" ({outcome.checkpoints} checkpoints saved in {outcome.checkpoint_s:.1f} s)"
             if outcome.checkpoints else "")
    console.print(f"wall {outcome.result.wall_s:.1f} s{saved}; results in {outcome.folder} "
                  f"(report: {outcome.report})")
    recording = outcome.recording
    if recording is not None and recording.failure is not None:  # its warning is printed above
        leave_without_rerun()
    elif recording is not None and recording.target.mode == "save":
        shown = recording.target.path
        console.print(f"rerun recording: {shown} (open with `rerun {shown}` or `pancam-graph view "
                      f"{outcome.folder}`)")
    if recording is not None and recording.target.mode == "serve":
        serve_until_interrupted(recording, serve_for_s)


@app.command("run", epilog=examples(
    "pancam-graph run denver_trail --seed 1 --configs vo,vo_sites --rerun spawn",
    "pancam-graph run tests/data/real/robot_localization/test1.bag --odom-topic /husky_velocity_controller/odom",
    "pancam-graph run ../shared/data/real/curiosity_navcam_sol26_57",
))
@with_source_options(*SourceOptions.flags())
def run_command(
    source: str | None = typer.Argument(None, help="bundled scenario name, a scenario TOML file, an "
                                        "observation folder, a rendered image folder, a ROS bag, a KITTI raw "
                                        "drive folder or a KITTI odometry sequence folder [default: denver_trail]"),
    out: Path | None = typer.Option(None, "--out", help="results folder (default: results/<name>-seed<N>-"
                                    "<YYYYmmdd-HHMMSS> for a scenario, results/<name>-<YYYYmmdd-HHMMSS> otherwise)"),
    configs: str | None = typer.Option(None, "--configs", help="configurations to run, comma-separated: names "
                                       "(vo, vo_sites, full, ...) or kinds joined by '+' (vo+gps); default: "
                                       "every configuration the source can feed"),
    batch: bool = typer.Option(False, "--batch", help="polish every estimate with batch Levenberg-Marquardt"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    rerun: str | None = typer.Option(None, "--rerun", help=rerun_help("recording.rrd")),
    viewer_memory: str = typer.Option("25%", "--viewer-memory", help="memory limit of a spawned or served viewer"),
    serve_for: float | None = typer.Option(None, "--serve-for", min=0.0, help=SERVE_FOR_HELP),
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
    vo_error_model: str | None = typer.Option(
        None, "--vo-error-model", help="the VO error model instead of the source's own ([estimator] "
        "vo_error_model): pixel_noise (white pixel noise, simulation) or real_images (the model measured on real "
        "images: docs/frontend.md)"),
    source_options: SourceOptions = SourceOptions(),
) -> None:
    """Solve a traverse with iSAM2 and evaluate it: every source goes through the same back-end.

    A scenario is simulated and compared with truth; an observation folder runs external
    observations; a ROS bag or a KITTI raw drive becomes a traverse with a stop at each GPS fix,
    scored on held-out fixes. Writes metrics.json, run.toml, trajectories (TUM, KITTI, WGS84 CSV,
    GeoJSON, KML; on Mars a CSV on the IAU 2015 sphere), plots and report.md into the results
    folder; a failed run leaves <out>.partial with what was done, which `--resume` continues.
    """
    from .. import api
    from ..runtime.processes import cores, start_process_server

    processes = 1 if one_process else None
    if resume is not None:
        given = {"SOURCE": source, "--out": out, "--configs": configs, "--batch": batch or None,
                 "--vo-error-model": vo_error_model}
        with user_input():
            clash = [name for name, value in given.items() if value is not None]
            clash += [SourceOptions.flags()[name] for name in source_options.given()]
            if clash:
                raise ConfigError(f"--resume goes on with the run's own source and options; drop {', '.join(clash)}")
            target = rerun_target(rerun, viewer_memory)
            point = api.resume_point(resume)
        n = len(point.data.traverse.stops)
        where = (f"at stop {point.states[0].next_stop}" if len(point.states) == 1 else "with its groups of "
                 "configurations at " + ", ".join(f"stop {s.next_stop} ({', '.join(s.localizers)})"
                                                  for s in point.states))
        console.print(f"resuming {point.data.traverse.name} {where} of {n} (from {point.partial})")
        _print_outcome(with_progress(point.data.traverse.name, quiet, lambda report: api.resume(
            point, processes=processes, rerun=target, checkpoint_every_s=checkpoint_every, figures=not no_plots,
            progress=report, on_viewer=announce_viewer)), serve_for)
        return
    source = source or "denver_trail"
    if processes is None and cores() > 1:
        start_process_server()  # it imports the package while the source loads
    with user_input():
        target = rerun_target(rerun, viewer_memory)
        names = parse_configs(configs)
        api.check_out(out)
        api.check_configs(source, names)  # before a long simulation or front-end
        data = with_progress(Path(source).name or source, quiet,
                              lambda report: api.open_data(source, source_options, out, report,
                                                           vo_error_model=vo_error_model, processes=processes))
        from ..solve.pipeline import select_configurations

        select_configurations(data.estimator, data.traverse, names)  # before anything is written
    for note in data.info.notes:
        console.print(Text("note: ", style="dim") + Text(note), soft_wrap=True)
    for reason in data.rejected[:10]:
        console.print(Text("fix left out: ", style="yellow") + Text(reason), soft_wrap=True)
    if len(data.rejected) > 10:
        console.print(Text(f"... {len(data.rejected) - 10} more fixes left out", style="yellow"), soft_wrap=True)
    _print_outcome(with_progress(data.traverse.name, quiet, lambda report: api.run(
        source, out=out, seed=source_options.seed, configs=names, batch=batch, processes=processes, rerun=target,
        checkpoint_every_s=checkpoint_every, figures=not no_plots, progress=report, opened=data,
        on_viewer=announce_viewer, vo_error_model=vo_error_model)), serve_for)

