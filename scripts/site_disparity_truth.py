"""The image front-end's site stereo disparities against the renderer's depth.

    python scripts/site_disparity_truth.py [SCENARIO] [--seed N] [--sites N] [--length-m M]

Renders the first --sites sites of SCENARIO (cut to its first --length-m metres, without
featureless stretches) as `pancam-graph render` renders them, exactly calibrated (the ideal
profile: no drawn calibration or pointing error), rectifies each WAC pair with the pair's
calibration, matches it as an image run's site panorama does (frontend/tracker.StereoTracker)
and compares each feature's disparity with f b / z, z the renderer's depth under the left pixel.
Prints the disparity error's median, mean and spread (1.4826 MAD) by range band: a bias here is
a range error every site carries (docs/simulation_errors.md, "Measurement level against
rendered images"; 2026-11-29, the defaults, mars_excerpt seed 5, two sites: median +0.002 px).
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from pancam_graph.config import FrontendConfig, load_scenario, resolve_scenario
from pancam_graph.frontend.tracker import StereoTracker
from pancam_graph.render.renderer import TerrainRenderer, sensor_image
from pancam_graph.render.scenario_images import raw_stereo_pair
from pancam_graph.render.terrain import terrain_tiles
from pancam_graph.sim import simulate
from pancam_graph.sim.world import dense_path

BANDS_M = ((1.5, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", nargs="?", default="mars_excerpt")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--sites", type=int, default=2)
    parser.add_argument("--length-m", type=float, default=120.0)
    args = parser.parse_args()

    bundled = load_scenario(resolve_scenario(args.scenario), errors="ideal")
    first = bundled.path.waypoints[0]
    ahead = [first[0] + args.length_m, first[1], first[2]]
    scenario = bundled.model_copy(update={
        "path": bundled.path.model_copy(update={"waypoints": [first, ahead], "sharp_turns": []}),
        "terrain": bundled.terrain.model_copy(update={"featureless": []})})
    traverse, truth = simulate(scenario, args.seed)
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), args.seed), seed=args.seed)
    calibration = raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m, scenario.render)
    stereo = calibration.rectified()
    rig = stereo.of(traverse.rig)
    left_raw, right_raw = calibration.cameras()
    rectify = calibration.rectification_maps()
    noise = np.random.default_rng(1)
    camera, baseline = rig.wac, rig.baseline_m

    rows = []  # measured disparity, true disparity, depth
    sites = [s for s in traverse.stops if s.is_site][:args.sites]
    for stop in sites:
        world_T_body = truth.world_T_body[stop.index]
        for frame in stop.panorama:
            world_T_raw_left = world_T_body @ traverse.rig.body_T_left(frame.pan_rad, frame.tilt_rad).matrix()
            raw = [sensor_image(renderer.render(world_T, cam), noise) for world_T, cam in
                   ((world_T_raw_left, left_raw), (world_T_raw_left @ calibration.left_T_right(), right_raw))]
            left, right = rectify(*raw)
            world_T_left = world_T_body @ rig.body_T_left(frame.pan_rad, frame.tilt_rad).matrix()
            depth = renderer.render_depth(world_T_left, camera).astype(np.float32)
            for u_left, u_right, v in StereoTracker(FrontendConfig())(left, right).uvv:
                z = float(cv2.getRectSubPix(depth, (1, 1), (float(u_left), float(v)))[0, 0])
                if BANDS_M[0][0] < z < BANDS_M[-1][1]:
                    rows.append((u_left - u_right, camera.fx * baseline / z, z))
    r = np.array(rows)
    error = r[:, 0] - r[:, 1]
    print(f"{args.scenario} seed {args.seed}: {len(sites)} sites, {len(r)} features; disparity error "
          f"median {np.median(error):+.3f} px, mean {error.mean():+.3f} px")
    for low, high in BANDS_M:
        band = error[(r[:, 2] >= low) & (r[:, 2] < high)]
        if len(band):
            spread = 1.4826 * np.median(np.abs(band - np.median(band)))
            print(f"  {low:4.1f}-{high:4.1f} m: {len(band):6d} features, median {np.median(band):+.3f}, "
                  f"mean {band.mean():+.3f}, spread {spread:.3f} px")


if __name__ == "__main__":
    main()
