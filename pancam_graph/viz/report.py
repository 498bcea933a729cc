"""The run report: a Markdown page with the dissertation's Chapter 4 figures and the metric table."""

from __future__ import annotations

from pathlib import Path

from ..evaluation.consistency import NEES_BOUND_99
from ..solve.results import RunResult
from ..store.documents import reproduce_command
from . import plots

FIGURES = (
    ("trajectories.png", plots.plot_trajectories,
     "Estimated and true trajectories with GPS fixes and sites (cf. the dissertation's Fig. 4.10)."),
    ("error_vs_distance.png", plots.plot_error_vs_distance,
     "3-D position error against distance travelled; dotted: the RMS error each configuration expects "
     "of itself (square root of the trace of its iSAM2 marginal)."),
    ("distance_relation.png", plots.plot_distance_relation,
     "Estimated against reference distance travelled and their difference (cf. the dissertation's Figs. 4.12-4.13: "
     "the dissertation's VO came out short)."),
    ("elevation_profile.png", plots.plot_elevation_profile,
     "Height against distance travelled (cf. the dissertation's Fig. 4.14)."),
)
NEES_FIGURE = ("nees_along_run.png", plots.plot_nees_along_run,
               "Each stop's position NEES against the reference (without truth: each GPS fix's, with the fix's "
               "own covariance added): a right covariance keeps it near 3 and puts 1 % above the 99 % bound "
               "(dashed).")


def _figures(result: RunResult) -> tuple:
    """The figures a run has: the NEES one needs a reference."""
    has_nees = any(c.nees is not None for c in result.configurations.values())
    return FIGURES + ((NEES_FIGURE,) if has_nees else ())


def write_report(result: RunResult, folder: Path, figures: bool = True) -> Path:
    """Write `report.md` and (unless `figures` is False) its PNG figures into `folder`; return
    the report's path."""
    if figures:
        for filename, plot, _ in _figures(result):
            plot(result, folder / filename)
    path = folder / "report.md"
    path.write_text(report_markdown(result, figures), encoding="utf-8")
    return path


def report_markdown(result: RunResult, figures: bool = True) -> str:
    tr = result.traverse
    stops = tr.stops
    length = result.reference_distance()[-1]
    where = " in this folder" if result.scenario is not None else ""
    lines = [
        f"# {result.title}",
        "",
        f"{result.description}",
        "",
        f"- rig: {tr.rig.name}; {len(stops)} stops over {length:.1f} m ({result.reference_positions()[1]}); "
        f"{sum(s.is_site for s in stops)} sites with panoramas; {len(tr.gps_fixes)} GPS fixes in the graph"
        + (f", {len(result.held_out_fixes)} held out" if result.held_out_fixes else ""),
        f"- source: {result.source.kind} `{result.source.path}`; reference: {result.source.reference}; "
        f"wall time {result.wall_s:.1f} s (VO {result.vo_s:.1f} s)",
        *(f"- note: {note}" for note in result.source.notes),
        f"- reproduce{where}: `{reproduce_command(result)}` (the whole configuration is in run.toml)",
        "",
        "## Metrics",
        "",
        "| config | kinds | avg err m | closure m | rel. closure % | ATE m unaligned / SE(3)-aligned | length ratio "
        "| distance scale | KITTI drift % | bridged | landmarks | GPS used / outliers | avg err vs GPS m "
        "| RMS 2-D vs held-out m |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, c in result.configurations.items():
        m, vs, held = c.metrics, c.metrics_vs_gps, c.holdout
        cells = ["-"] * 7
        if m is not None:
            drift = "-" if m.drift_translation_pct is None else f"{m.drift_translation_pct:.3f}"
            cells = [f"{m.average_error_m:.3f}", f"{m.closure_error_m:.3f}", f"{m.relative_closure_pct:.4f}",
                     f"{m.ate_unaligned_rmse_m:.3f} / {m.ate_se3_rmse_m:.3f}", f"{m.length_ratio:.5f}",
                     f"{plots.distance_scale(result, name):.5f}", drift]
        lines.append(
            f"| {name} | {'+'.join(c.kinds)} | {' | '.join(cells)} | {c.bridged_stops} | {c.landmarks} "
            f"| {c.counter('gps_fixes_used')} / {c.counter('gps_outliers')} "
            f"| {'-' if vs is None else f'{vs.average_error_m:.2f}'} "
            f"| {'-' if held is None else f'{held.rms_2d_m:.3f} (stated {held.stated_drms_m:.3f})'} |"
        )
    lines += [
        "",
        "Relative closure is the closure error over the reference length (docs/design.md section 5); "
        "ATE is the RMS position error after the stated alignment (none for configurations with GPS); "
        "distance scale is the least-squares slope of estimated against reference distance travelled; "
        "a GPS outlier is a fix failing the chi-square test at the estimate after its update; held-out fixes are "
        "never in any graph.",
        "",
        *_covariance_section(result),
    ]
    if figures:
        lines += ["## Figures", ""]
        for filename, _, caption in _figures(result):
            lines += [f"![{filename}]({filename})", "", caption, ""]
    return "\n".join(lines)


def _covariance_section(result: RunResult) -> list[str]:
    """Whether each configuration's covariance can be trusted, stop by stop (where a reference is)."""
    rows = [(name, c) for name, c in result.configurations.items() if c.nees is not None]
    if not rows:
        return []
    gps = any(c.nees.against == "gps" for _, c in rows)
    what, last = ("GPS fixes", "last fix's") if gps else ("stops", "last stop's")
    lines = ["## Covariance along the run", "",
             *([("No truth: each GPS fix is the reference, at the stop nearest it in time, with the fix's own "
                 "stated covariance added to the estimate's."), ""] if gps else []),
             f"| config | {last} NEES (99 % bound {NEES_BOUND_99:.1f}) | {what} outside their 99 % "
             f"ellipsoid | ANEES | largest NEES: stop (NEES, VO inliers) |", "|---|---|---|---|---|"]
    for name, c in rows:
        anees = c.nees.anees if c.consistency is None else c.consistency.anees
        largest = ", ".join(f"{c.nees.stops[k]} ({c.nees.nees[k]:.1f}, "
                            f"{c.nees.vo_inliers[k] if c.nees.vo_inliers[k] >= 0 else '-'})" for k in c.nees.largest())
        lines.append(f"| {name} | {c.nees.last:.2f} | {100 * c.nees.outside_99_fraction:.1f} % | {anees:.2f} "
                     f"| {largest} |")
    lines += ["", "A right covariance puts about 1 % of the stops outside their 99 % ellipsoid, with a mean NEES "
              "of 3 (ANEES 1); stops along a run are correlated, so one run's figures scatter more than "
              "independent samples would.", ""]
    return lines
