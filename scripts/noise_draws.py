"""One traverse, many draws of its measurement noise: where does one run's closure sit?

    python scripts/noise_draws.py SCENARIO --seed N --draws K --out DIR [--configs vo,vo_sites]
                                  [--against METRICS.json ...]

Runs SCENARIO's seed N K times at measurement level, each with another `noise_seed` (the rover's
pixels, tracking, ties, odometry, GPS and start survey drawn anew; the world, path, sites,
calibration and mast pointing the seed's own), and prints each configuration's closure over the
draws: median, 10th-90th percentile, and how often two draws agree within a factor of 1.5. Each
`--against` run (say an image run of the same scenario and seed, whose world, calibration and
pointing are these) is placed among the draws: its percentile and its ratio to their median.
Draws already in DIR are read, not run again. 2026-11-29 (docs/simulation_errors.md, "One seed,
many noise draws"): denver_trail seed 0, 30 draws, `vo_sites` median 0.048 %, 10th-90th
0.019-0.084 %, two draws within 1.5 of each other 0.38 of the time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import pancam_graph
from pancam_graph.config import dump_scenario, load_scenario, resolve_scenario


def closures(folder: Path, configs: list[str]) -> dict[str, float]:
    metrics = json.loads((folder / "metrics.json").read_text())["configs"]
    return {c: metrics[c]["relative_closure_pct"] for c in configs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--configs", default="vo,vo_sites")
    parser.add_argument("--against", type=Path, nargs="*", default=[], help="metrics.json of runs to place")
    args = parser.parse_args()
    configs = args.configs.split(",")
    scenario = load_scenario(resolve_scenario(args.scenario))
    draws: list[dict[str, float]] = []
    for k in range(args.draws):
        folder = args.out / f"draw_{k}"
        if not (folder / "metrics.json").exists():
            args.out.mkdir(parents=True, exist_ok=True)
            toml = args.out / f"draw_{k}.toml"
            toml.write_text(dump_scenario(scenario.model_copy(update={"noise_seed": k})))
            pancam_graph.run(toml, seed=args.seed, configs=tuple(configs), out=folder, figures=False)
        draws.append(closures(folder, configs))
        print(f"draw {k}: " + "  ".join(f"{c} {v:.3f} %" for c, v in draws[-1].items()), flush=True)
    for c in configs:
        d = np.array([x[c] for x in draws])
        log = np.log(d)
        pairs = np.abs(log[:, None] - log[None, :])[np.triu_indices(len(d), 1)]
        print(f"{c}: median {np.median(d):.3f} %, 10th-90th {np.percentile(d, 10):.3f}-{np.percentile(d, 90):.3f} %; "
              f"two draws within 1.5 of each other {np.mean(pairs < np.log(1.5)):.2f} of the time")
        for path in args.against:
            x = closures(path.parent, [c])[c]
            percentile = 100 * (np.sum(d < x) + 0.5) / (len(d) + 1)
            print(f"  {path.parent}: {x:.3f} %, percentile {percentile:.0f}, "
                  f"{x / np.median(d):.2f} x the median")


if __name__ == "__main__":
    main()
