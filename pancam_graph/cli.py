"""Command line: the only place that parses arguments, prints and chooses exit codes."""

from __future__ import annotations

import json
import resource
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from .config import ConfigError, dump_scenario, load_scenario, resolve_scenario
from .errors import PancamGraphError
from .pipeline import RunOptions, RunResult, metrics_document, percentiles, run

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Rover localization over long traverses with a GTSAM factor graph.")
console = Console(stderr=True)
EXIT_USAGE = 2  # bad input: scenario file, options
EXIT_FAILURE = 1  # the run itself failed


def _load(scenario: str):
    return load_scenario(resolve_scenario(scenario))


def _fail(exc: PancamGraphError) -> typer.Exit:
    console.print(f"[bold red]error:[/] {exc}", markup=True, highlight=False)
    return typer.Exit(EXIT_USAGE if isinstance(exc, ConfigError) else EXIT_FAILURE)


def _run_with_progress(scenario, options: RunOptions, quiet: bool = False) -> RunResult:
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console, transient=True, disable=quiet) as bar:
        task = bar.add_task(f"{scenario.name}: stops", total=None)

        def report(stage: str, done: int, total: int) -> None:
            bar.update(task, description=f"{scenario.name}: {stage}", completed=done, total=total)

        return run(scenario, options, progress=report)


def _summary_table(result: RunResult) -> Table:
    table = Table(title=f"{result.scenario.name} (seed {result.seed}, {len(result.traverse.stops)} stops)")
    for col in ("config", "avg err m", "closure m", "rel. closure %", "ATE m", "length ratio",
                "drift %", "bridged", "landmarks", "vs GPS avg m"):
        table.add_column(col, justify="right")
    for name, c in result.configurations.items():
        m = c.metrics
        vs = c.metrics_vs_gps
        table.add_row(
            name, f"{m.average_error_m:.2f}", f"{m.closure_error_m:.2f}", f"{m.relative_closure_pct:.3f}",
            f"{m.ate_rmse_m:.2f} ({m.ate_alignment.split()[0]})", f"{m.length_ratio:.4f}",
            "-" if m.drift_translation_pct is None else f"{m.drift_translation_pct:.2f}",
            str(c.bridged_stops), str(c.landmarks), "-" if vs is None else f"{vs.average_error_m:.2f}",
        )
    return table


def _write_results(result: RunResult, out: Path) -> None:
    from .io.results import results_folder, write_csv, write_json, write_tum
    from .viz.plots import plot_error_vs_distance, plot_trajectories

    times = np.array([s.time_s for s in result.traverse.stops])
    with results_folder(out) as folder:
        (folder / "scenario.toml").write_text(dump_scenario(result.scenario), encoding="utf-8")
        write_json(folder / "metrics.json", metrics_document(result))
        write_tum(folder / "truth.tum", times, result.truth.world_T_body)
        for name, c in result.configurations.items():
            write_tum(folder / f"trajectory_{name}.tum", times, c.world_T_body)
        write_csv(folder / "gps_fixes.csv",
                  ["stop", "time_s", "lat_deg", "lon_deg", "h_ellipsoidal_m", "sigma_h_m", "sigma_v_m"],
                  [(s.index, s.time_s, f"{s.gps.lat_deg:.9f}", f"{s.gps.lon_deg:.9f}", f"{s.gps.h_m:.4f}",
                    s.gps.sigma_horizontal_m, s.gps.sigma_vertical_m)
                   for s in result.traverse.stops if s.gps is not None])
        write_csv(folder / "motions.csv", ["stop", "source", "vo_inliers", "vo_failure"],
                  [(k, m.source, m.vo_inliers, m.vo_failure)
                   for k, m in enumerate(result.motions) if m is not None])
        plot_trajectories(result, folder / "trajectories.png")
        plot_error_vs_distance(result, folder / "error_vs_distance.png")


@app.command("run")
def run_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or path to a TOML file"),
    out: Path | None = typer.Option(None, "--out", help="results folder (default: results/<scenario>-seed<N>-<time>)"),
    seed: int | None = typer.Option(None, "--seed", help="override the scenario's seed"),
    no_gps: bool = typer.Option(False, "--no-gps", help="skip the configuration that uses GPS"),
    no_sites: bool = typer.Option(False, "--no-sites", help="skip configurations that use site panoramas"),
    no_hrc: bool = typer.Option(False, "--no-hrc", help="skip configurations that use the HRC"),
    batch: bool = typer.Option(False, "--batch", help="polish every estimate with batch Levenberg-Marquardt"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Simulate a traverse, solve every configuration with iSAM2, compare with truth and GPS."""
    try:
        sc = _load(scenario)
        options = RunOptions(seed=seed, use_gps=not no_gps, use_sites=not no_sites, use_hrc=not no_hrc, batch=batch)
        seed_used = sc.seed if seed is None else seed
        out = out or Path("results") / f"{sc.name}-seed{seed_used}-{datetime.now():%Y%m%d-%H%M%S}"
        result = _run_with_progress(sc, options, quiet)
        _write_results(result, out)
    except PancamGraphError as exc:
        raise _fail(exc) from None
    Console(width=150).print(_summary_table(result))
    console.print(f"wall {result.wall_s:.1f} s; results in {out}")


@app.command("bench")
def bench_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or path to a TOML file"),
    seed: int | None = typer.Option(None, "--seed", help="first seed (default: the scenario's)"),
    seeds: int = typer.Option(1, "--seeds", min=1, help="run this many consecutive seeds and summarise"),
) -> None:
    """Time full runs (all configurations) and print one JSON object."""
    try:
        sc = _load(scenario)
        first = sc.seed if seed is None else seed
        results, walls = [], []
        for s in range(first, first + seeds):
            start = time.perf_counter()
            results.append(run(sc, RunOptions(seed=s)))
            walls.append(time.perf_counter() - start)
            if seeds > 1:
                console.print(f"seed {s}: {walls[-1]:.1f} s")
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
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
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
    print(json.dumps(report, indent=2))


@app.command("scenarios")
def scenarios_command() -> None:
    """List the bundled scenarios."""
    from .config import bundled_scenarios

    for name, path in sorted(bundled_scenarios().items()):
        try:
            description = load_scenario(path).description
        except ConfigError as exc:
            description = f"(invalid: {exc})"
        print(f"{name:16s} {description}")


if __name__ == "__main__":
    app()
