"""Registration of every site to the orbital DTM against the truth, at measurement level.

    python scripts/orbital_registration_study.py SCENARIO SEED [SEED ...] [--offset-m 2.0]

Simulates the scenario, then registers each site's panorama points to the simulated map from
the true pose seen through the true map bias, moved by a random horizontal offset (1 sigma
--offset-m per axis) and yaw error (0.3 deg): what the predicted pose of a run gives the
registration. Prints the horizontal error's median and 95th percentile, the NEES of each
component against the registration's covariance, and the time per site.
"""

from __future__ import annotations

import argparse
import time

import gtsam
import numpy as np

from pancam_graph.config import bundled_scenarios, load_scenario
from pancam_graph.dem_registration import DtmErrors, RegistrationFailed, register_site
from pancam_graph.graph import tie_gate
from pancam_graph.kinds.orbital import BIAS_NAMES, OrbitalSettings, _map_pose, predicted_measurement
from pancam_graph.sim import simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("seeds", type=int, nargs="+")
    parser.add_argument("--offset-m", type=float, default=2.0)
    args = parser.parse_args()
    path = bundled_scenarios().get(args.scenario, args.scenario)
    scenario = load_scenario(path)
    settings: OrbitalSettings = scenario.estimator.orbital
    errors = DtmErrors(settings.surface_sigma_m, settings.dtm_sigma_m, settings.dtm_correlation_m)
    horizontal, components, seconds, failed = [], [], [], 0
    for seed in args.seeds:
        traverse, truth = simulate(scenario, seed)
        orbital_map = traverse.measurements["orbital"][0]
        true_bias = np.array([truth.kinds["orbital"][f"map0_{n}"] for n in BIAS_NAMES])
        rng = np.random.default_rng(seed)
        for stop in (s for s in traverse.stops if s.is_site):
            pose = gtsam.Pose3(truth.world_T_body[stop.index])
            true = predicted_measurement(pose, true_bias)
            guess = _map_pose(pose, true_bias)
            guess[:2, 3] += rng.normal(0.0, args.offset_m, 2)
            guess[:3, :3] = gtsam.Rot3.Yaw(rng.normal(0.0, np.deg2rad(0.3))).matrix() @ guess[:3, :3]
            points, covs = tie_gate.site_point_cloud(stop, traverse.rig, traverse.image_noise_px)
            rotation = truth.world_T_body[stop.index][:3, :3]
            vertical = np.einsum("i,nij,j->n", rotation[2], covs, rotation[2])
            start = time.perf_counter()
            try:
                result = register_site(points, vertical, guess, orbital_map.dtm, traverse.origin,
                                       search_m=float(np.clip(3 * args.offset_m, *settings.search_m)),
                                       errors=errors, max_range_m=settings.max_range_m,
                                       min_points=settings.min_points, min_distinctness=settings.min_distinctness)
            except RegistrationFailed as exc:
                failed += 1
                print(f"seed {seed} stop {stop.index}: {exc}")
                continue
            seconds.append(time.perf_counter() - start)
            error = result.measurement - true
            error[3] = (error[3] + np.pi) % (2 * np.pi) - np.pi
            horizontal.append(float(np.hypot(*error[:2])))
            if horizontal[-1] > 0.8:
                print(f"  seed {seed} stop {stop.index}: error {error.round(2)}, sigma "
                      f"{np.sqrt(np.diag(result.covariance)).round(2)}, {result.points} points, "
                      f"distinctness {result.distinctness:.0f}")
            components.append(error**2 / np.diag(result.covariance))
    horizontal, components = np.array(horizontal), np.array(components)
    print(f"{len(horizontal)} sites registered, {failed} failed")
    print(f"horizontal error: median {np.median(horizontal):.3f} m, "
          f"95th percentile {np.percentile(horizontal, 95):.3f} m")
    print("NEES per component (east, north, up, yaw), 1 if the covariance is right: "
          + ", ".join(f"{v:.2f}" for v in components.mean(axis=0)))
    print(f"time per site: median {np.median(seconds) * 1000:.0f} ms, largest {np.max(seconds) * 1000:.0f} ms")


if __name__ == "__main__":
    main()
