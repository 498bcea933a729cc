"""Sun-sensor heading over many seeds of a scenario: each configuration with and without the
sun_heading kind, the heading error at every site with a sighting against the sun sensor's 3
sigma there, the final position error and the Monte Carlo ANEES with its band.

    .venv/bin/python scripts/sun_heading_study.py long_traverse --seeds 10 --out sun_study.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.evaluation.consistency import Consistency, monte_carlo_summary
from pancam_graph.solve.pipeline import run_scenario
from pancam_graph.solve.results import RunOptions

PAIRS = {"dead_reckoning": "dead_reckoning+wheel_slip+sun_heading", "vo_sites": "vo+sites+sun_heading"}


def heading_deg(world_T_body: np.ndarray) -> np.ndarray:
    """The body x axis' azimuth in the world, counter-clockwise from east (degrees)."""
    return np.rad2deg(np.arctan2(world_T_body[..., 1, 0], world_T_body[..., 0, 0]))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--pairs", default="dead_reckoning,vo_sites")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    scenario = load_scenario(resolve_scenario(args.scenario))
    pairs = {base: PAIRS[base] for base in args.pairs.split(",")}
    configs = tuple(c for pair in pairs.items() for c in pair)
    sensor_sigma = np.deg2rad(scenario.estimator.sun_heading.sigma_deg)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        t0 = time.perf_counter()
        result = run_scenario(scenario, RunOptions(seed=seed, configs=configs, processes=2))
        truth = result.truth.world_T_body
        sightings = result.traverse.measurements.get("sun_heading", ())
        row = {"seed": seed, "sightings": len(sightings), "wall_s": time.perf_counter() - t0, "configs": {}}
        for name, config in result.configurations.items():
            est = config.world_T_body
            entry = {"final_error_m": float(np.linalg.norm(est[-1, :3, 3] - truth[-1, :3, 3])),
                     "ate_rmse_m": config.metrics.ate_rmse_m, "anees": config.consistency.anees,
                     "rmse_m": config.consistency.rmse_m, "crlb_rms_m": config.consistency.crlb_rms_m,
                     "counters": {k: v for k, v in config.counters.items() if k.startswith("sun_")}}
            stops = np.array([s.stop for s in sightings], dtype=int)
            if len(stops):
                error = (heading_deg(est[stops]) - heading_deg(truth[stops]) + 180.0) % 360.0 - 180.0
                reference = np.array([truth[s.stop][:3, :3] @ s.sun_body for s in sightings])
                elevation = np.arcsin(np.clip(reference[:, 2], -1, 1))
                bound = np.rad2deg(3 * sensor_sigma / np.cos(elevation))  # sun sensor's 3 sigma in heading
                entry |= {"heading_error_max_deg": float(np.max(np.abs(error))),
                          "heading_error_rms_deg": float(np.sqrt(np.mean(error**2))),
                          "sites_within_3sigma": int(np.sum(np.abs(error) <= bound)), "sites": len(stops),
                          "worst_error_over_bound": float(np.max(np.abs(error) / bound))}
            row["configs"][name] = entry
        rows.append(row)
        print(json.dumps({"seed": seed, **{n: {k: round(v, 3) for k, v in e.items() if isinstance(v, float)}
                                         for n, e in row["configs"].items()}}), flush=True)
        runs = {name: [] for name in configs}
        summary = {}
        for name in configs:
            for r in rows:
                c = r["configs"][name]
                runs[name].append(Consistency(c["rmse_m"], c["crlb_rms_m"], c["rmse_m"] / c["crlb_rms_m"],
                                              c["anees"], (0.0, 0.0)))
            summary[name] = monte_carlo_summary(runs[name]) | {
                "final_error_m_mean": float(np.mean([r["configs"][name]["final_error_m"] for r in rows]))}
        args.out.write_text(json.dumps({"scenario": args.scenario, "rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
