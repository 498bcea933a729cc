"""Figures of the error analysis, after the dissertation's Figs. 3.5-3.14."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.patches import Ellipse as EllipsePatch

from ..analysis.design import Assumptions
from ..analysis.trades import SEED_TABLE_3_2, RigAnalysis, analysis_document
from .plots import _label, _save, plt


def plot_ellipses(row: RigAnalysis, sigma_px: float, path: Path) -> None:
    """Fig. 3.5-3.7: features in the FOV and their 95 % error ellipses (to scale)."""
    fig, ax = plt.subplots(figsize=(6, 7))
    for (x, z), e in zip(row.points, row.ellipses, strict=True):
        ax.add_patch(EllipsePatch((x, z), 2 * e.semi_major_m, 2 * e.semi_minor_m, angle=np.rad2deg(e.angle_rad),
                                  fill=False, color="tab:blue", lw=0.8))
    ax.plot(row.points[:, 0], row.points[:, 1], ".", color="k", ms=2)
    half = np.deg2rad(row.rig.fov_deg) / 2
    r = np.hypot(*row.points.T).max()
    ax.plot([0, r * np.sin(-half), np.nan, 0, r * np.sin(half)], [0, r * np.cos(half), np.nan, 0, r * np.cos(half)],
            color="tab:gray", lw=0.8, label=f"FOV {row.rig.fov_deg:.1f} deg")
    ax.set_aspect("equal")
    _label(ax, "X across (m)", "Z range (m)",
           f"{row.rig.name}: 95 % error ellipses, B = {row.rig.baseline_m} m, f = {row.rig.focal_px:.0f} px, "
           f"sigma = {sigma_px} px")
    _save(fig, path)


def plot_vo_vs_features(rows: list[RigAnalysis], path: Path) -> None:
    """Fig. 3.8: stop-2 sigma of two-stop VO vs the number of features (max range 10-20 m)."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in rows:
        if row.features_curve is not None:
            ax.plot(row.features_curve.x, 1e3 * row.features_curve.y, "o-", label=row.features_curve.label)
    _label(ax, "features seen from both stops", "stop-2 position sigma (mm)", "Two-stop VO, 2 m step")
    _save(fig, path)


def plot_vo_vs_distance(rows: list[RigAnalysis], path: Path) -> None:
    """Fig. 3.9: stop-2 sigma vs the distance between the two stops."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in rows:
        if row.step_curve is not None:
            ax.plot(row.step_curve.x, 1e3 * row.step_curve.y, label=row.rig.name)
    _label(ax, "distance between stops (m)", "stop-2 position sigma (mm)", "Two-stop VO vs distance travelled")
    _save(fig, path)


def plot_hrc_gain(row: RigAnalysis, path: Path) -> None:
    """Fig. 3.11: two-stop VO with the stereo WAC alone and with the HRC for features in its FOV."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(row.step_curve.x, 1e3 * row.step_curve.y, "--", label=row.step_curve.label)
    ax.plot(row.step_curve_hrc.x, 1e3 * row.step_curve_hrc.y, "-.", label=row.step_curve_hrc.label)
    _label(ax, "distance between stops (m)", "stop-2 position sigma (mm)",
           f"{row.rig.name}: HRC + left WAC for features in the HRC's {row.rig.hrc_fov_deg:.1f} deg FOV")
    _save(fig, path)


def plot_error_vs_fov(rows: list[RigAnalysis], spacing_m: float, path: Path) -> None:
    """Fig. 3.13: relative error vs FOV at a fixed site spacing, by number of tie points."""
    fig, axes = plt.subplots(1, len(rows), figsize=(4 * len(rows), 4), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        for curve in row.fov_curves:
            ax.plot(curve.x, curve.y, label=curve.label)
            ax.plot(curve.x[np.argmin(curve.y)], curve.y.min(), "k.")
        _label(ax, "FOV (deg)", "relative error (%)", f"{row.name}, sites {spacing_m:g} m apart")
    _save(fig, path)


def plot_error_vs_spacing(rows: list[RigAnalysis], target: float, path: Path) -> None:
    """Fig. 3.14: relative error vs site spacing at each rig's optimal FOV, and the 1 % line."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in rows:
        line, = ax.plot(row.spacing_curve.x, row.spacing_curve.y,
                        label=f"{row.name} ({row.optimal_fov_deg:.0f} deg): {row.max_site_spacing_m:.1f} m")
        ax.plot(row.max_site_spacing_m, 100 * target, "o", color=line.get_color())
    ax.axhline(100 * target, color="k", lw=0.8, ls=":")
    _label(ax, "site spacing (m)", "relative error (%)", "Two-site BA, 9 tie points: longest spacing for 1 %")
    _save(fig, path)


def table_markdown(rows: list[RigAnalysis], a: Assumptions) -> str:
    """Table 3.2 with the dissertation's figures beside ours, and the assumptions."""
    lines = ["# Two-site BA: longest site spacing for 1 % relative error (cf. the dissertation's Table 3.2)", "",
             "| rig | B (m) | f (px) | optimal FOV (deg) | dissertation | FOV, 16 tie points | max spacing (m) "
             "| dissertation | ours / dissertation | simulated BA there (%) | rigid model there (%) "
             "| rigid: max spacing (m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        seed = SEED_TABLE_3_2.get(row.name, {})
        b, f = (row.rig.hrc_baseline_m, row.rig.hrc_focal_px) if row.hrc else (row.rig.baseline_m, row.rig.focal_px)
        ratio = f"{row.max_site_spacing_m / seed['max_site_spacing_m']:.2f}" if seed else "-"
        check = row.two_site_check
        simulated = "-" if check is None else "{:.2f} ({:.2f}-{:.2f})".format(
            100 * check.simulated, *(100 * x for x in check.simulated_interval))
        rigid = "-" if check is None else f"{100 * check.predicted_rigid:.2f}"
        rigid_spacing = "-" if row.rigid_max_site_spacing_m is None else f"{row.rigid_max_site_spacing_m:.1f}"
        lines.append(f"| {row.name} | {b:g} | {f:.0f} | {row.optimal_fov_deg:.0f} | {seed.get('optimal_fov_deg', '-')} "
                     f"| {row.optimal_fov_16_deg:.0f} | {row.max_site_spacing_m:.1f} "
                     f"| {seed.get('max_site_spacing_m', '-')} | {ratio} | {simulated} | {rigid} | {rigid_spacing} |")
    lines += ["", "## Assumptions (the same for every rig)", ""]
    lines += [f"- `{k}`: {v}" for k, v in a.as_dict().items()]
    lines += ["", "## Notes", ""] + [f"- {note}" for note in analysis_document(rows, a)["notes"]]
    return "\n".join(lines) + "\n"


def write_analysis(rows: list[RigAnalysis], a: Assumptions, out: Path) -> list[Path]:
    """analysis.json, table_3_2.md and the figures into `out`; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []

    def target(name: str) -> Path:
        written.append(out / name)
        return out / name

    target("analysis.json").write_text(json.dumps(analysis_document(rows, a), indent=2) + "\n")
    target("table_3_2.md").write_text(table_markdown(rows, a))
    wac_rows = [row for row in rows if not row.hrc]
    for row in wac_rows:
        plot_ellipses(row, a.sigma_px, target(f"fig_3_5_ellipses_{row.name}.png"))
    plot_vo_vs_features(wac_rows, target("fig_3_8_vo_sigma_vs_features.png"))
    plot_vo_vs_distance(wac_rows, target("fig_3_9_vo_sigma_vs_distance.png"))
    for row in wac_rows:
        if row.step_curve_hrc is not None:
            plot_hrc_gain(row, target(f"fig_3_11_hrc_gain_{row.name}.png"))
    plot_error_vs_fov(rows, a.ba_fov_reference_spacing_m, target("fig_3_13_relative_error_vs_fov.png"))
    plot_error_vs_spacing(rows, a.relative_error_target, target("fig_3_14_relative_error_vs_spacing.png"))
    return written
