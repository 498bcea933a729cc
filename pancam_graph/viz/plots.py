"""Static PNG plots of a run: trajectories (like the seed's Fig. 4.10) and error vs distance."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..pipeline import RunResult, gps_enu  # noqa: E402

_COLOURS = {"vo": "tab:red", "vo_sites": "tab:orange", "vo_sites_hrc": "tab:green", "full": "tab:blue"}


def plot_trajectories(result: RunResult, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    _, gps = gps_enu(result.traverse)
    if len(gps):
        ax.scatter(gps[:, 0], gps[:, 1], s=3, c="0.6", label="GPS fixes", zorder=1)
    truth = result.truth.positions
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=2.0, label="truth", zorder=2)
    for name, c in result.configurations.items():
        p = c.world_T_body[:, :3, 3]
        ax.plot(p[:, 0], p[:, 1], "-", lw=1.2, color=_COLOURS.get(name), zorder=3,
                label=f"{name} (closure {c.metrics.relative_closure_pct:.2f} %)")
    sites = [s.index for s in result.traverse.stops if s.is_site]
    ax.plot(truth[sites, 0], truth[sites, 1], "k^", ms=5, label="sites (panoramas)", zorder=4)
    ax.plot(*truth[0, :2], "go", ms=8, label="start")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{result.scenario.name}, seed {result.seed}: estimated vs true trajectory")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_error_vs_distance(result: RunResult, path: Path) -> None:
    truth = result.truth.positions
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth, axis=0), axis=1))])
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    for name, c in result.configurations.items():
        err = np.linalg.norm(c.world_T_body[:, :3, 3] - truth, axis=1)
        ax.plot(dist, err, color=_COLOURS.get(name), lw=1.2, label=name)
    bridged = [k for k, m in enumerate(result.motions) if m is not None and m.bridged]
    if bridged:
        ax.plot(dist[bridged], np.zeros(len(bridged)), "|", color="k", ms=12, label="VO bridged")
    ax.set_xlabel("distance travelled (m)")
    ax.set_ylabel("3-D position error (m)")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("position error against distance travelled")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
