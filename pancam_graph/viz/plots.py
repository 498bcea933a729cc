"""Static PNG plots of a run, after the dissertation's Chapter 4 figures: trajectories (Fig. 4.10),
error and travelled distance against the reference distance (Figs. 4.12-4.13) and the
elevation profile (Fig. 4.14)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..evaluation.consistency import NEES_BOUND_99  # noqa: E402
from ..evaluation.evaluate import Evaluation  # noqa: E402
from ..evaluation.gps_check import antenna_at_times, gps_enu  # noqa: E402
from ..solve.results import RunResult, travelled  # noqa: E402

_COLOURS = {"dead_reckoning": "tab:purple", "dead_reckoning_gps": "tab:brown", "vo": "tab:red",
            "vo_sites": "tab:orange", "vo_sites_hrc": "tab:green", "full": "tab:blue"}


def plot_trajectories(result: RunResult, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    _, gps = gps_enu(result.traverse)
    if len(gps):
        ax.scatter(gps[:, 0], gps[:, 1], s=3, c="0.6", label="GPS fixes", zorder=1)
    _, held = gps_enu(result.traverse, result.held_out_fixes)
    if len(held):
        ax.scatter(held[:, 0], held[:, 1], s=6, marker="x", c="tab:red", label="held-out GPS fixes", zorder=1)
    truth, _ = result.reference_positions()
    if result.truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], "k-", lw=2.0, label="truth", zorder=2)
    for name, c in result.configurations.items():
        p = c.world_T_body[:, :3, 3]
        score = (f"closure {c.metrics.relative_closure_pct:.2f} %" if c.metrics is not None else
                 f"held-out RMS {c.holdout.rms_2d_m:.2f} m" if c.holdout is not None else "")
        ax.plot(p[:, 0], p[:, 1], "-", lw=1.2, color=_COLOURS.get(name), zorder=3, label=f"{name} ({score})")
    sites = [s.index for s in result.traverse.stops if s.is_site]
    if sites:
        ax.plot(truth[sites, 0], truth[sites, 1], "k^", ms=5, label="sites (panoramas)", zorder=4)
    ax.plot(*truth[0, :2], "go", ms=8, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    x, y = result.source.axes
    _label(ax, f"{x} (m)", f"{y} (m)", f"{result.title}: estimated trajectories")
    _save(fig, path)


def distance_scale(result: RunResult, name: str) -> float:
    """Least-squares slope (through the origin) of estimated against reference travelled distance:
    below 1, the estimate comes out short (the dissertation's Fig. 4.12 found 0.93 for its VO)."""
    ref = result.reference_distance()
    est = travelled(result.configurations[name].world_T_body[:, :3, 3])
    return float(ref @ est / (ref @ ref))


def plot_error_vs_distance(result: RunResult, path: Path) -> None:
    if result.truth is None:
        _plot_gps_error(result, path)
        return
    truth = result.truth.positions
    dist = result.reference_distance()
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    largest = 0.0
    for name, c in result.configurations.items():
        err = np.linalg.norm(c.world_T_body[:, :3, 3] - truth, axis=1)
        largest = max(largest, float(err.max()))
        ax.plot(dist, err, color=_COLOURS.get(name), lw=1.2, label=name)
        # sqrt(trace) of the marginal is the RMS error the estimator expects of itself
        predicted = np.sqrt(np.trace(c.position_covariance, axis1=1, axis2=2))
        ax.plot(dist, predicted, color=_COLOURS.get(name), lw=0.8, ls=":")
    ax.plot([], [], color="0.3", lw=0.8, ls=":", label="expected RMS (iSAM2 marginal)")
    bridged = [k for k, m in enumerate(result.motions) if m is not None and m.bridged]
    if bridged:
        ax.plot(dist[bridged], np.zeros(len(bridged)), "|", color="k", ms=12, label="VO bridged")
    # linear below a hundredth of the largest error, logarithmic above: two decades with ticks
    # whatever the scale (a fixed 0.1 m left a 51-frame KITTI run with the ticks 0 and 0.1 only)
    ax.set_yscale("symlog", linthresh=10.0 ** np.floor(np.log10(max(largest, 1e-3) / 100.0)))
    _label(ax, "distance travelled (m)", "3-D position error (m)", "position error against distance travelled")
    _save(fig, path)


def plot_nees_along_run(result: RunResult, path: Path) -> None:
    """Each stop's position NEES (or each GPS fix's, without truth) against the distance
    travelled, with its mean (3) and 99 % bound when the covariance is right: above the bound the
    estimate claims more than it knows."""
    dist = result.reference_distance()
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    for name, c in result.configurations.items():
        if c.nees is not None:
            # NEES 0 at the start pose (the prior fixes it): kept visible on the log axis
            ax.plot(dist[c.nees.stops], np.maximum(c.nees.nees, 1e-3), color=_COLOURS.get(name), lw=1.0,
                    marker="o" if c.nees.against == "gps" else None, ms=3,
                    label=f"{name} ({100 * c.nees.outside_99_fraction:.0f} % "
                          f"{'of GPS fixes' if c.nees.against == 'gps' else 'of stops'} above)")
    ax.axhline(NEES_BOUND_99, color="k", lw=1.0, ls="--", label=f"99 % bound ({NEES_BOUND_99:.1f})")
    ax.axhline(3.0, color="0.5", lw=0.8, ls=":", label="mean of a right covariance (3)")
    ax.set_yscale("log")
    _label(ax, "distance travelled (m)", "position NEES (3 dof)", "does the covariance hold along the run?")
    _save(fig, path)


def _plot_gps_error(result: RunResult, path: Path) -> None:
    """Without truth: each configuration's antenna against the held-out fixes (or, with none held
    out, against the fixes in the graph), horizontally."""
    fixes = result.held_out_fixes or result.traverse.gps_fixes
    what = "held-out GPS fixes" if result.held_out_fixes else "GPS fixes in the graph"
    times, enu = gps_enu(result.traverse, fixes)
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    dist = travelled(enu)
    for name, c in result.configurations.items():
        antenna = antenna_at_times(result.traverse, c.world_T_body, times)
        ax.plot(dist, np.linalg.norm(antenna[:, :2] - enu[:, :2], axis=1), color=_COLOURS.get(name), lw=1.0,
                label=name)
    sigma = np.array([f.sigma_horizontal_m for f in fixes])
    ax.plot(dist, np.sqrt(2.0) * sigma, color="0.4", lw=0.8, ls=":", label="fixes' stated 2-D RMS")
    _label(ax, "distance along the fixes (m)", f"horizontal distance to the {what} (m)",
           f"position against the {what}")
    _save(fig, path)


def plot_distance_relation(result: RunResult, path: Path) -> None:
    """Estimated against reference travelled distance (the dissertation's Fig. 4.12) and their difference."""
    ref = result.reference_distance()
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110)
    left.plot(ref, ref, "k-", lw=2.0, label=f"reference ({result.reference_positions()[1]})")
    for name, c in result.configurations.items():
        est = travelled(c.world_T_body[:, :3, 3])
        label = f"{name} (scale {distance_scale(result, name):.4f})"
        left.plot(ref, est, color=_COLOURS.get(name), lw=1.2, label=label)
        right.plot(ref, est - ref, color=_COLOURS.get(name), lw=1.2, label=name)
    right.axhline(0.0, color="k", lw=1.0)
    _label(left, "reference distance travelled (m)", "estimated distance travelled (m)",
           "accumulated distance: estimate vs reference")
    _label(right, "reference distance travelled (m)", "estimated - reference distance (m)",
           "distance difference (scale error shows as a slope)")
    _save(fig, path)


def plot_elevation_profile(result: RunResult, path: Path) -> None:
    """Height against reference travelled distance (the dissertation's Fig. 4.14)."""
    ref = result.reference_distance()
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    times, gps = gps_enu(result.traverse)
    if len(times):
        arm = result.traverse.gps_lever_arm_m[2]
        at_fix = np.interp(times, [s.time_s for s in result.traverse.stops], ref)
        ax.scatter(at_fix, gps[:, 2] - arm, s=3, c="0.6", zorder=1,
                   label=f"GPS fixes (antenna height - {arm:.2f} m lever arm)")
    if result.truth is not None:
        ax.plot(ref, result.truth.positions[:, 2], "k-", lw=2.0, label="truth", zorder=2)
    for name, c in result.configurations.items():
        ax.plot(ref, c.world_T_body[:, 2, 3], color=_COLOURS.get(name), lw=1.2, label=name, zorder=3)
    _label(ax, "reference distance travelled (m)", "up (m, local ENU)", "elevation profile")
    _save(fig, path)


def _label(ax, xlabel: str, ylabel: str, title: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def evaluation_plot(evaluation: Evaluation, path: Path) -> None:
    """`pancam-graph eval`: both tracks in plan and the position error along the reference."""
    est, ref = evaluation.estimate.positions, evaluation.reference.positions
    fig, (plan, err) = plt.subplots(1, 2, figsize=(13, 5.5), dpi=110)
    plan.plot(ref[:, 0], ref[:, 1], "k-", lw=2.0, label=f"reference: {Path(evaluation.reference.source).name}")
    plan.plot(est[:, 0], est[:, 1], "-", color="tab:blue", lw=1.2,
              label=f"estimate: {Path(evaluation.estimate.source).name} (alignment {evaluation.alignment})")
    plan.plot(*ref[0, :2], "go", ms=8, label="start")
    plan.set_aspect("equal", adjustable="datalim")
    _label(plan, "east (m)", "north (m)", "trajectories")
    distance = travelled(ref)
    err.plot(distance, np.linalg.norm(est - ref, axis=1), "-", color="tab:blue", lw=1.0, label="3-D")
    err.plot(distance, np.linalg.norm(est[:, :2] - ref[:, :2], axis=1), "-", color="tab:orange", lw=1.0,
             label="horizontal")
    _label(err, "distance along the reference (m)", "position error (m)",
           f"ATE RMSE {evaluation.metrics.ate_rmse_m:.3f} m")
    _save(fig, path)


def plot_cost_along(per_km: dict[str, list[dict]], memory: dict[str, list[dict]], title: str, path: Path) -> None:
    """bench's cost against distance: each configuration's iSAM2 update median (line) and p99
    (dashed) per window of path, and each group of configurations' process's resident memory
    along the path. Flat is bounded."""
    fig, (ax, mem) = plt.subplots(2, 1, figsize=(9, 7), dpi=110, sharex=True, height_ratios=[2, 1])
    for name, windows in per_km.items():
        km = [(w["from_m"] + 500.0) / 1000.0 for w in windows]
        colour = _COLOURS.get(name)
        ax.plot(km, [w["median"] for w in windows], "-o", ms=3, color=colour, label=f"{name} median")
        ax.plot(km, [w["p99"] for w in windows], "--", color=colour, alpha=0.6)
    ax.set_yscale("log")
    _label(ax, "", "iSAM2 update per stop (ms)", f"{title}: cost along the traverse (dashed: p99)")
    for group, samples in memory.items():
        mem.plot([m["at_m"] / 1000.0 for m in samples], [m["rss_mb"] for m in samples], label=group)
    _label(mem, "distance along the path (km)", "resident memory (MB)", "")
    _save(fig, path)
