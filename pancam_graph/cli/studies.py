"""The commands that study results: view (rerun), eval, sweep, bench, analyze."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from ..config import SourceOptions
from ..errors import ConfigError, ResultsError
from .app import EXIT_FAILURE, app, console, leave_without_rerun, user_input
from .common import (
    SERVE_FOR_HELP,
    announce_viewer,
    examples,
    has_display,
    progress_bar,
    rerun_help,
    rerun_target,
    serve_until_interrupted,
    with_progress,
)


@app.command("view", epilog=examples(
    "pancam-graph view results/denver_trail-seed0-20261127-120000 --rerun serve",
))
def view_command(
    results: Path = typer.Argument(..., help="a results folder written by `pancam-graph run`"),
    rerun: str | None = typer.Option(None, "--rerun", help=rerun_help("replay.rrd") + " [default: spawn where "
                                     "there is a display, else save]"),
    viewer_memory: str = typer.Option("25%", "--viewer-memory", help="memory limit of a spawned or served viewer"),
    serve_for: float | None = typer.Option(None, "--serve-for", min=0.0, help=SERVE_FOR_HELP),
) -> None:
    """Replay a finished results folder into rerun with the live run's layout."""
    from ..api import view
    from ..store.results_folder import read_run

    with user_input():
        saved = read_run(results)  # a folder that is not a run is the first thing to hear of
        if rerun is None:
            rerun = "spawn" if has_display() else "save"
            if rerun == "save":
                console.print(f"note: no display: the replay is saved to {results / 'replay.rrd'} (or give "
                              "--rerun serve for a web viewer)")
        target = rerun_target(rerun, viewer_memory)
    recording = view(results, target, saved, on_viewer=announce_viewer)
    if recording.failure is not None:  # the replay is all view makes
        leave_without_rerun()
        raise ResultsError(recording.failure)
    if recording.target.mode == "save":
        console.print(f"rerun recording: {recording.target.path}")
    elif recording.target.mode == "serve":
        serve_until_interrupted(recording, serve_for)


@app.command("eval", epilog=examples(
    "pancam-graph eval results/run/trajectory_vo.tum results/run/truth.tum --align se3",
    "pancam-graph eval results/run/trajectory_full.tum results/run/gps_fixes.csv",
))
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
    lever_arm: str | None = typer.Option(None, "--lever-arm", help="X,Y,Z: the GPS antenna in the body frame (m), "
                                         "where an estimate with attitudes is compared with a GPS log (default: "
                                         "the run's, in local_frame.json beside the estimate)"),
    out: Path | None = typer.Option(None, "--out", help="write metrics.json (and a plot) into this folder"),
) -> None:
    """Compare two trajectories, or a trajectory with a GPS log, with the run's metrics."""
    from ..api import evaluate

    with user_input():
        frame = _three_numbers("--origin", origin, "LAT,LON,H in degrees and metres")
        arm = _three_numbers("--lever-arm", lever_arm, "X,Y,Z in metres")
        result = evaluate(estimate, reference, align=align, max_dt_s=max_dt, rpe_delta_m=rpe_delta, origin=frame,
                          gps_sigma_m=gps_sigma, lever_arm=arm, out=out)
    m = result.metrics
    at = "" if result.lever_arm_m is None else f", at the antenna {list(result.lever_arm_m)} m"
    table = Table(title=escape(f"{estimate.name} vs {reference.name} ({len(result.reference)} matched, "
                               f"{result.association}, alignment {result.alignment}{at})"))
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


def _three_numbers(flag: str, text: str | None, expected: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise ConfigError(f"{flag} {text!r}: expected {expected}")
    return values


@app.command("sweep", epilog=examples(
    "pancam-graph sweep spec.toml --out sweeps/relin --workers 2",
))
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
    summary.csv (efficiency and ANEES over the seeds, as `bench --monte-carlo`, and the last stop's
    NEES against the exact band of independent runs). A run that
    fails or times out is recorded (runs_status.csv) and the others go on."""
    from ..api import plan_sweep, sweep

    with user_input():
        planned = plan_sweep(spec, out, scheduler)
    start = time.perf_counter()
    with progress_bar(quiet) as bar:
        task = bar.add_task(f"{escape(spec.stem)}: runs", total=len(planned.runs))

        def report(record, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)
            if record.status in ("failed", "timeout"):
                bar.console.print(Text(f"{record.run.name}: {record.status}: {record.message}", style="yellow"),
                                  soft_wrap=True)

        outcome = sweep(planned, workers=workers, scheduler=scheduler, progress=report)
    runs, summary = planned.runs, outcome.summary
    table = Table(title=f"{escape(spec.stem)}: {len(runs)} runs", box=None, padding=(0, 1))
    for column in ("scenario", "rig", "variant", "config", "runs", "closure %", "ATE m", "efficiency", "ANEES",
                   "last stop NEES/3"):
        table.add_column(column)
    for row in summary:
        table.add_row(escape(row.scenario), row.rig, escape(row.variant), escape(row.config), str(row.runs),
                      f"{row.closure_pct_mean:.3f}", f"{row.ate_m_mean:.2f}",
                      "-" if row.efficiency is None else f"{row.efficiency:.2f}",
                      "-" if row.anees is None else f"{row.anees:.2f} ({row.covariance})",
                      "-" if row.nees_last is None else f"{row.nees_last:.2f} ({row.last_stop_covariance})")
    Console(width=160).print(table)  # every column on one line: a summary is read side by side
    counts = {status: outcome.count(status) for status in ("done", "skipped", "failed", "timeout")}
    console.print(f"wall {time.perf_counter() - start:.1f} s; " + ", ".join(f"{n} {k}" for k, n in counts.items())
                  + f"; tables in {out} (runs.csv, summary.csv, runs_status.csv)")
    if counts["failed"] or counts["timeout"]:
        raise typer.Exit(EXIT_FAILURE)


@app.command("bench", epilog=examples(
    "pancam-graph bench denver_trail --monte-carlo 30 --workers 2",
    "pancam-graph bench sites images/",
))
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
    from ..api import bench

    def report(stage: str, done: int, total: int) -> None:
        if stage.startswith("seed "):  # a finished seed of several: one line each
            console.print(stage)

    if scenario in ("frontend", "sites"):
        with user_input():
            if scenario == "sites":
                document = with_progress("sites", False, lambda p: bench.bench_sites(source, progress=p))
            else:
                document = with_progress("front-end", False, lambda p: bench.bench_frontend(
                    source, SourceOptions(detector=detector).detector, progress=p))
    elif source is not None or detector is not None:
        raise ConfigError("SOURCE and --detector go with 'bench frontend' only")
    elif monte_carlo and workers:
        document = bench.bench_monte_carlo_sweep(scenario, seed, max(seeds, monte_carlo), workers)
    else:
        document = bench.bench_runs(scenario, seed, seeds, rerun, monte_carlo, plot,
                                    report if seeds > 1 or rerun or monte_carlo else None)
    print(json.dumps(document, indent=2))


@app.command("analyze", epilog=examples(
    "pancam-graph analyze --rig exomars --rig mer_navcam --out analysis/",
))
def analyze_command(
    rig: list[str] = typer.Option(None, "--rig", help="rig preset (repeatable; default: every preset)"),
    out: Path = typer.Option(Path("results/analysis"), "--out", help="folder for analysis.json, "
                                                                     "table_3_2.md and the figures"),
    sigma_px: float = typer.Option(0.5, "--sigma-px", min=0.01, help="matching error of x_l and x_r (px)"),
    baseline: float | None = typer.Option(None, "--baseline", min=0.01, help="custom rig: stereo baseline (m)"),
    focal_px: float | None = typer.Option(None, "--focal-px", min=1.0, help="custom rig: focal length (px)"),
    fov_deg: float | None = typer.Option(None, "--fov", min=1.0, max=179.0, help="custom rig: horizontal FOV (deg)"),
) -> None:
    """The dissertation's Chapter 3 error analysis for each rig: mapping ellipses, two-stop VO, the HRC's
    gain and the two-site BA (optimal FOV, longest site spacing for 1 %), as figures, a Table 3.2
    and analysis.json; every assumption is written with them."""
    from ..analysis.trades import SEED_TABLE_3_2
    from ..api import analyze

    custom = [baseline, focal_px, fov_deg]
    if any(v is not None for v in custom) and not all(v is not None for v in custom):
        raise ConfigError("a custom rig needs --baseline, --focal-px and --fov together")
    start = time.perf_counter()
    outcome = with_progress("analysing rigs", False, lambda report: analyze(
        out, rig, sigma_px, tuple(custom) if baseline is not None else None,
        progress=lambda done, total: report("rigs", done, total)))
    rows, assumptions, written = outcome.rows, outcome.assumptions, outcome.files
    table = Table(title=f"two-site BA, {assumptions.tie_points} tie points, sigma {sigma_px} px")
    for column in ("rig", "optimal FOV deg", "FOV, 16 tie points", "max spacing for 1 % (m)", "dissertation (m)",
                   "simulated BA there %", "rigid model there %"):
        table.add_column(column, justify="right")
    for row in rows:
        seed = SEED_TABLE_3_2.get(row.name, {}).get("max_site_spacing_m", "-")
        check = row.two_site_check
        simulated = ("-", "-") if check is None else (f"{100 * check.simulated:.2f}",
                                                      f"{100 * check.predicted_rigid:.2f}")
        table.add_row(row.name, f"{row.optimal_fov_deg:.0f}", f"{row.optimal_fov_16_deg:.0f}",
                      f"{row.max_site_spacing_m:.1f}", str(seed), *simulated)
    console.print(table)
    console.print(f"{len(written)} files in {out} ({time.perf_counter() - start:.1f} s); "
                  f"assumptions and notes in {out / 'table_3_2.md'}")

