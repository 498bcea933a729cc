"""Registration of every site to the orbital DTM against the truth.

    python scripts/orbital_registration_study.py SCENARIO SEED [SEED ...] [--offset-m 2.0]
        [--images {ties,dense,both,ortho,all}] [--cell-m 0.5 [1.0 ...]] [--every N] [--save FILE.npz]

Simulates the scenario, then registers each site's local elevation map to the simulated map
from the true pose seen through the true map bias, moved by a random horizontal offset (1 sigma
--offset-m per axis) and yaw error (0.3 deg): what the predicted pose of a run gives the
registration. Prints the horizontal error's median and 95th percentile, the NEES of each
component against the registration's covariance, the time per site, and how the errors of
neighbouring sites are correlated (they register on overlapping patches of the same DTM).

The site's elevation map is, by default, the panorama's simulated tie points (measurement
level). With --images, each site's WAC pairs are rendered as `pancam-graph render` renders them
(raw, distorted, a misaligned right camera; the map is made of the rendered ground) and
rectified with the pair's calibration: "ties" are the image front-end's features
(frontend/panorama.py), "dense<cell>" is OpenCV SGBM on every rectified pair gridded to one point
per --cell-m cell (frontend/dense_stereo.py). "ortho" is the site's ground patch from the same
SGBM (dense_stereo.ground_patch) correlated with the map's orthoimage, rendered from above under
the orbiter's sun (ortho_registration.py): east and north only (up and yaw print as 0).
--every N registers every N-th site only (rendering a site takes a minute).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import gtsam
import numpy as np

from pancam_graph.config import FrontendConfig, bundled_scenarios, load_scenario
from pancam_graph.graph import tie_gate
from pancam_graph.kinds.orbital import BIAS_NAMES, OrbitalSettings, _map_pose, predicted_measurement
from pancam_graph.orbital.dem_registration import DtmErrors, RegistrationFailed, register_site
from pancam_graph.records import PanoramaFrame
from pancam_graph.sim import simulate


def measured_clouds(scenario, seed: int, every: int):
    """Per site (every `every`-th): traverse, truth, the stop and {"ties": (points, covariances)}
    of its simulated tie points."""
    traverse, truth = simulate(scenario, seed)
    sites = [s for s in traverse.stops if s.is_site][::every]
    for stop in sites:
        yield traverse, truth, stop, {"ties": tie_gate.site_point_cloud(stop, traverse.rig, traverse.image_noise_px)}


def rendered_clouds(scenario, seed: int, every: int, modes: tuple[str, ...], cells_m: tuple[float, ...]):
    """The same from each site's rendered WAC pairs: the front-end's features ("ties") and SGBM's
    dense points gridded at each of `cells_m` ("dense<cell>")."""
    from pancam_graph.frontend.dense_stereo import dense_site_points, elevation_map, ground_patch
    from pancam_graph.frontend.panorama import PanoramaMatcher, PanoramaView
    from pancam_graph.render.renderer import TerrainRenderer, sensor_image
    from pancam_graph.render.scenario_images import maps_of_rendered_ground, raw_stereo_pair
    from pancam_graph.render.terrain import terrain_tiles
    from pancam_graph.sim.world import dense_path

    started = time.perf_counter()
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), seed), seed=seed)
    traverse, truth = maps_of_rendered_ground(scenario, *simulate(scenario, seed), seed, renderer)
    print(f"terrain and orthoimage: {time.perf_counter() - started:.0f} s")
    mounted = traverse.rig
    calibration = raw_stereo_pair(mounted.wac, mounted.baseline_m, scenario.render)
    left_camera, right_camera = calibration.cameras()
    left_T_right = calibration.left_T_right()
    rectify = calibration.rectification_maps()
    stereo = calibration.rectified()
    # what reading the folder makes of the rig (store/observation_folder._rig)
    rig = stereo.of(mounted)
    rng = np.random.default_rng([seed, 3])
    matcher = PanoramaMatcher(rig.wac, rig.baseline_m, FrontendConfig())
    noise = scenario.render.sensor_noise_dn
    sites = [s for s in traverse.stops if s.is_site][::every]
    for n, stop in enumerate(sites):
        started = time.perf_counter()
        world_T_body = truth.world_T_body[stop.index]
        views = []
        for f in stop.panorama:
            world_T_left = world_T_body @ mounted.body_T_left(f.pan_rad, f.tilt_rad).matrix()
            left = sensor_image(renderer.render(world_T_left, left_camera), rng, noise)
            right = sensor_image(renderer.render(world_T_left @ left_T_right, right_camera), rng, noise)
            views.append(PanoramaView(f.pan_rad, f.tilt_rad, rig.body_T_left(f.pan_rad, f.tilt_rad).matrix(),
                                      *rectify(left, right)))
        rendered = time.perf_counter() - started
        clouds = {}
        if "ties" in modes:
            site = matcher(stop.index, stop.site_id, views)
            seen = replace(stop, panorama=tuple(PanoramaFrame(v.pan_rad, v.tilt_rad, v.observations)
                                                for v in site.views))
            clouds["ties"] = tie_gate.site_point_cloud(seen, rig, traverse.image_noise_px)
        if "dense" in modes:
            points = dense_site_points(views, rig.wac, rig.baseline_m)
            for cell in cells_m:
                clouds[f"dense{cell:g}"] = None if points is None else elevation_map(*points, cell)
        if "ortho" in modes:
            clouds["ortho"] = ground_patch(views, rig.wac, rig.baseline_m)
        print(f"site {n + 1}/{len(sites)} (stop {stop.index}): rendered in {rendered:.0f} s, "
              + ", ".join(f"{k} {_size(c)} points" for k, c in clouds.items()), flush=True)
        yield traverse, truth, stop, clouds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("seeds", type=int, nargs="+")
    parser.add_argument("--offset-m", type=float, default=2.0)
    parser.add_argument("--images", choices=["ties", "dense", "both", "ortho", "all"])
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--cell-m", type=float, nargs="+", default=[0.5], help="dense: elevation map cells")
    parser.add_argument("--save", help="write each registration's error, covariance and place (.npz)")
    args = parser.parse_args()
    scenario = load_scenario(bundled_scenarios().get(args.scenario, args.scenario))
    settings: OrbitalSettings = scenario.estimator.orbital
    errors = DtmErrors(settings.surface_sigma_m, settings.dtm_sigma_m, settings.dtm_correlation_m)
    modes = {"both": ("ties", "dense"), "all": ("ties", "dense", "ortho")}.get(args.images, (args.images or "ties",))
    names = [m for m in modes if m != "dense"] + ([f"dense{c:g}" for c in args.cell_m] if "dense" in modes else [])
    rows: dict[str, list] = {m: [] for m in names}
    failed = dict.fromkeys(names, 0)
    for seed in args.seeds:
        clouds = (rendered_clouds(scenario, seed, args.every, modes, tuple(args.cell_m)) if args.images
                  else measured_clouds(scenario, seed, args.every))
        rng = np.random.default_rng(seed)
        for traverse, truth, stop, by_mode in clouds:
            orbital_map = traverse.measurements["orbital"][0]
            true_bias = np.array([truth.kinds["orbital"][f"map0_{n}"] for n in BIAS_NAMES])
            pose = gtsam.Pose3(truth.world_T_body[stop.index])
            true = predicted_measurement(pose, true_bias)
            guess = _map_pose(pose, true_bias)
            guess[:2, 3] += rng.normal(0.0, args.offset_m, 2)
            guess[:3, :3] = gtsam.Rot3.Yaw(rng.normal(0.0, np.deg2rad(0.3))).matrix() @ guess[:3, :3]
            up = truth.world_T_body[stop.index][2, :3]
            for mode, cloud in by_mode.items():
                if cloud is None:
                    failed[mode] += 1
                    continue
                try:
                    if mode == "ortho":
                        result = _ortho(cloud, guess, orbital_map, traverse.origin, 3 * args.offset_m, true)
                    else:
                        points, covs = cloud
                        result = register_site(points, np.einsum("i,nij,j->n", up, covs, up), guess,
                                               orbital_map.dtm, traverse.origin,
                                               float(np.clip(3 * args.offset_m, *settings.search_m)),
                                               errors, settings.max_range_m, settings.min_points,
                                               settings.min_distinctness)
                except RegistrationFailed as exc:
                    failed[mode] += 1
                    print(f"  {mode}: seed {seed} stop {stop.index}: {exc}")
                    continue
                error = result.measurement - true
                error[3] = (error[3] + np.pi) % (2 * np.pi) - np.pi
                rows[mode].append((seed, stop.index, *truth.world_T_body[stop.index][:2, 3], *error,
                                   *result.covariance.ravel(), result.seconds))
                if np.hypot(*error[:2]) > 0.8:
                    print(f"  {mode}: seed {seed} stop {stop.index}: error {error.round(2)}, sigma "
                          f"{np.sqrt(np.diag(result.covariance)).round(2)}")
    for name in names:
        _summary(name, np.array(rows[name]), failed[name])
    if args.save:
        np.savez(args.save, **{m: np.array(r) for m, r in rows.items()})


def _size(cloud) -> int:
    """Points of an elevation map (points, covariances) or cells of a ground patch."""
    return 0 if cloud is None else len(cloud[0]) if isinstance(cloud, tuple) else len(cloud.grey)


def _ortho(patch, guess: np.ndarray, orbital_map, frame, search_m: float, true: np.ndarray):
    """The orthoimage correlation as a 4-component result: up and yaw taken as the truth's."""
    from types import SimpleNamespace

    from pancam_graph.orbital.ortho_registration import register_patch

    if orbital_map.orthoimage is None:
        raise RegistrationFailed("the map has no orthoimage")
    found = register_patch(patch, guess, orbital_map.orthoimage, frame, search_m)
    covariance = np.eye(4)
    covariance[:2, :2] = found.covariance
    return SimpleNamespace(measurement=np.array([*found.measurement, *true[2:]]), covariance=covariance,
                           seconds=found.seconds)


def _summary(mode: str, rows: np.ndarray, failed: int) -> None:
    """Columns: seed, stop, true east, north, error (4), covariance (16), seconds."""
    print(f"\n{mode}: {len(rows)} sites registered, {failed} failed")
    if not len(rows):
        return
    error, cov = rows[:, 4:8], rows[:, 8:24].reshape(-1, 4, 4)
    horizontal = np.hypot(error[:, 0], error[:, 1])
    print(f"horizontal error: median {np.median(horizontal):.3f} m, "
          f"95th percentile {np.percentile(horizontal, 95):.3f} m, largest {horizontal.max():.3f} m")
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    print("NEES per component (east, north, up, yaw), 1 if the covariance is right: "
          + ", ".join(f"{v:.2f}" for v in (error**2 / sigma**2).mean(axis=0)))
    seconds = rows[:, 24]
    print(f"time per site: median {np.median(seconds) * 1000:.0f} ms, largest {np.max(seconds) * 1000:.0f} ms")
    # neighbouring sites of one seed: the correlation of their normalised errors, by distance
    z = error / sigma
    same = rows[1:, 0] == rows[:-1, 0]
    apart = np.hypot(*(rows[1:, 2:4] - rows[:-1, 2:4]).T)[same]
    pairs = z[1:][same] * z[:-1][same]
    if len(pairs) > 10:
        print("correlation of consecutive sites' normalised errors (east, north, up, yaw): "
              + ", ".join(f"{v:+.2f}" for v in pairs.mean(axis=0))
              + f" over {len(pairs)} pairs {np.median(apart):.0f} m apart (median)")


if __name__ == "__main__":
    main()
