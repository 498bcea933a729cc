"""The image front-end's site stereo disparities against the renderer's depth.

    python scripts/site_disparity_truth.py [SCENARIO] [--seed N] [--sites N] [--length-m M]
                                           [--errors ideal|realistic]

Renders the first --sites sites of SCENARIO (cut to its first --length-m metres, without
featureless stretches) as `pancam-graph render` renders them, rectifies each WAC pair with the
pair's calibration, matches it as an image run's site panorama does (frontend/tracker.StereoTracker)
and compares each feature's right-image column with where the pair puts the renderer's point
under the left pixel: the calibrated pair (`--errors ideal`, the default: exactly rendered, so
the disparity error is the front-end's) or the pair as the realistic profile drew it (`--errors
realistic`: rendered through the drawn calibration and at the mast's true angles, the column
predicted through that exact pair, sim/errors.TrueRig; a residual there is the renderer's or the
front-end's, not the drawn error's). Prints the error's median, mean and spread (1.4826 MAD) by
range band, and its fit over the image (constant, x, x^2, y, x y, x and y in focal lengths): a
constant is a disparity bias every site carries (docs/simulation_errors.md, "Measurement level
against rendered images"). 2026-11-29, two sites each: mars_excerpt seed 5, ideal, median -0.002 px
(of disparity +0.002); short_trail seed 0, realistic, median -0.008 px where the drawn error itself
moves the column by +0.129 px on average.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from pancam_graph.config import FrontendConfig, load_scenario, resolve_scenario
from pancam_graph.frontend.tracker import StereoTracker
from pancam_graph.geometry.calibration_error import NAMES
from pancam_graph.render.renderer import TerrainRenderer, sensor_image
from pancam_graph.render.scenario_images import as_built, raw_stereo_pair
from pancam_graph.render.terrain import terrain_tiles
from pancam_graph.sim import simulate
from pancam_graph.sim.errors import TrueRig
from pancam_graph.sim.world import dense_path

BANDS_M = ((1.5, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", nargs="?", default="mars_excerpt")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--sites", type=int, default=2)
    parser.add_argument("--length-m", type=float, default=120.0)
    parser.add_argument("--errors", choices=("ideal", "realistic"), default="ideal")
    args = parser.parse_args()

    bundled = load_scenario(resolve_scenario(args.scenario), errors=args.errors)
    first = bundled.path.waypoints[0]
    ahead = [first[0] + args.length_m, first[1], first[2]]
    scenario = bundled.model_copy(update={
        "path": bundled.path.model_copy(update={"waypoints": [first, ahead], "sharp_turns": []}),
        "terrain": bundled.terrain.model_copy(update={"featureless": []})})
    traverse, truth = simulate(scenario, args.seed)
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), args.seed), seed=args.seed)
    calibration = raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m, scenario.render)
    rig = calibration.rectified().of(traverse.rig)
    drawn = truth.kinds.get("stereo_calibration")
    left_raw, right_raw, left_T_right = as_built(calibration, drawn)
    rectify = calibration.rectification_maps()
    noise = np.random.default_rng(1)
    camera, baseline = rig.wac, rig.baseline_m
    exact = TrueRig.of_state(rig, drawn or dict.fromkeys(NAMES, 0.0))

    rows = []  # u_left, u_right measured, v, depth
    sites = [s for s in traverse.stops if s.is_site][:args.sites]
    for stop in sites:
        world_T_body = truth.world_T_body[stop.index]
        angles = truth.mast_angles.get(stop.index) or [(f.pan_rad, f.tilt_rad) for f in stop.panorama]
        for pan, tilt in angles[:len(stop.panorama)]:  # the panorama's frames come first
            world_T_raw_left = world_T_body @ traverse.rig.body_T_left(pan, tilt).matrix()
            raw = [sensor_image(renderer.render(world_T, cam), noise) for world_T, cam in
                   ((world_T_raw_left, left_raw), (world_T_raw_left @ left_T_right, right_raw))]
            left, right = rectify(*raw)
            world_T_left = world_T_body @ rig.body_T_left(pan, tilt).matrix()
            depth = renderer.render_depth(world_T_left, camera).astype(np.float32)
            for u_left, u_right, v in StereoTracker(FrontendConfig())(left, right).uvv:
                z = float(cv2.getRectSubPix(depth, (1, 1), (float(u_left), float(v)))[0, 0])
                if BANDS_M[0][0] < z < BANDS_M[-1][1]:
                    rows.append((u_left, u_right, v, z))
    r = np.array(rows)
    p = exact.left_point(r[:, 0], r[:, 2], r[:, 3])  # the renderer's point under the left pixel
    _, u_right_exact = exact.observe(p)
    error = r[:, 1] - u_right_exact
    shift = u_right_exact - (r[:, 0] - camera.fx * baseline / r[:, 3])
    print(f"{args.scenario} seed {args.seed} ({args.errors}): {len(sites)} sites, {len(r)} features; right column "
          f"error median {np.median(error):+.3f} px, mean {error.mean():+.3f} px (the drawn error's own shift: mean "
          f"{shift.mean():+.3f} px)")
    for low, high in BANDS_M:
        band = error[(r[:, 3] >= low) & (r[:, 3] < high)]
        if len(band):
            spread = 1.4826 * np.median(np.abs(band - np.median(band)))
            print(f"  {low:4.1f}-{high:4.1f} m: {len(band):6d} features, median {np.median(band):+.3f}, "
                  f"mean {band.mean():+.3f}, spread {spread:.3f} px")
    x, y = (r[:, 1] - camera.cx) / camera.fx, (r[:, 2] - camera.cy) / camera.fx
    kept = np.abs(error - np.median(error)) < 2.0
    terms = np.column_stack([np.ones_like(x), x, x * x, y, x * y])[kept]
    fit = np.linalg.lstsq(terms, error[kept], rcond=None)[0]
    print("  over the image (px): " + ", ".join(f"{name} {value:+.4f}" for name, value in
                                               zip(("constant", "x", "x^2", "y", "x y"), fit, strict=True)))


if __name__ == "__main__":
    main()
