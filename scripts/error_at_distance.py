"""Position error against distance travelled, over the runs of a sweep, for each configuration.

    python scripts/error_at_distance.py SWEEP_OUT [--at 1000 2000 5000 10000] [--plot OUT.png]

Reads every run's truth.tum and trajectory_<config>.tum under SWEEP_OUT/runs/ and prints, per
configuration, the horizontal and 3-D error (median and largest over the runs) at each distance
of `--at` (metres of the true path), with the ATE (RMS over all stops, in the world frame as it
stands: no alignment) and each run's largest error after the first kilometre. With --plot, the
median and the band between the smallest and largest run against distance.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def read_tum(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#")[:, 1:4]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path)
    parser.add_argument("--at", type=float, nargs="+", default=[1000.0, 2000.0, 5000.0, 10000.0])
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()
    runs = sorted(p for p in (args.sweep / "runs").iterdir() if (p / "truth.tum").is_file())
    errors: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for run in runs:
        truth = read_tum(run / "truth.tum")
        distance = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth, axis=0), axis=1))])
        for path in sorted(run.glob("trajectory_*.tum")):
            config = path.stem.removeprefix("trajectory_")
            estimate = read_tum(path)
            errors.setdefault(config, []).append((distance, np.linalg.norm(estimate[:, :2] - truth[:, :2], axis=1),
                                                  np.linalg.norm(estimate - truth, axis=1)))
    print(f"{len(runs)} runs in {args.sweep}")
    header = " ".join(f"{f'{d / 1000:g} km (h / 3-D)':>17}" for d in args.at)
    print(f"{'configuration':<20} {header}   ATE 3-D     max h after 1 km")
    for config, series in errors.items():
        cells = []
        for d in args.at:
            at = [(h[np.searchsorted(dist, d)], e[np.searchsorted(dist, d)]) for dist, h, e in series
                  if dist[-1] >= d]
            if not at:
                cells.append(f"{'-':>17}")
                continue
            h, e = np.array(at).T
            cells.append(f"{np.median(h):6.2f} / {np.median(e):6.2f} m")
        ate = [np.sqrt(np.mean(e**2)) for _, _, e in series]
        late = [h[dist > 1000.0].max() for dist, h, _ in series if dist[-1] > 1000.0]
        after = f"{np.median(late):5.2f} m (max {np.max(late):5.2f})" if late else "-"
        print(f"{config:<20} {' '.join(cells)}   {np.median(ate):5.2f} m (max {np.max(ate):5.2f})   {after}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
        for config, series in errors.items():
            grid = np.linspace(0.0, min(dist[-1] for dist, _, _ in series), 400)
            h = np.array([np.interp(grid, dist, err) for dist, err, _ in series])
            line, = ax.plot(grid / 1000, np.median(h, axis=0), lw=1.3, label=f"{config} (median)")
            ax.fill_between(grid / 1000, h.min(axis=0), h.max(axis=0), color=line.get_color(), alpha=0.2)
        ax.set_xlabel("distance travelled (km)")
        ax.set_ylabel("horizontal position error (m)")
        ax.set_title(f"error against distance, {len(runs)} runs (band: smallest to largest)")
        ax.set_yscale("symlog", linthresh=0.1)
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
