"""A scenario rendered as an image folder: the navigation stereo pair at every stop and the
site panoramas (WAC pairs, HRC frames) as PNG images, taken through a real lens by a real,
slightly misaligned stereo pair whose calibration goes with them; the traverse's timing, GPS
and odometry beside them and, in their own files, the truth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import gtsam
import numpy as np
from pyproj import CRS

from ..config import RenderConfig, Scenario
from ..errors import ResultsError
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera
from ..geometry.stereo_pair import StereoCalibration
from ..kinds.orbital import Orbital, OrbitalSensor
from ..orbital.maps import MapBias
from ..records import GroundTruth, MapRaster, Traverse
from ..runtime.processes import heap_for_image_work
from ..sim import kind_rng, simulate
from ..sim.world import dense_path
from ..store.observation_manifest import PanoramaImage
from ..store.observation_writer import write_observations
from .renderer import TerrainRenderer, sensor_image
from .terrain import Ground, terrain_tiles


def raw_stereo_pair(camera: Camera, baseline_m: float, config: RenderConfig) -> StereoCalibration:
    """The navigation pair as built: the rig's intrinsics through a distorting lens, and a right
    camera with its own small focal, principal point and pointing errors."""
    left = replace(camera, k1=config.distortion[0], k2=config.distortion[1], p1=config.distortion[2],
                   p2=config.distortion[3])
    dx, dy = config.right_principal_offset_px
    right = replace(left, fx=left.fx * config.right_focal_scale, fy=left.fy * config.right_focal_scale,
                    cx=left.cx + dx, cy=left.cy + dy)
    right_R_left = cv2.Rodrigues(np.deg2rad(np.array(config.right_rotation_deg, dtype=float)))[0]
    translation = -right_R_left @ np.array([baseline_m, 0.0, 0.0])  # right centre at +baseline along x
    return StereoCalibration("calibration.yaml", left.matrix(), left.distortion(), right.matrix(),
                             right.distortion(), (camera.width, camera.height), right_R_left, translation)


@heap_for_image_work()  # images and their buffers from the heap (runtime/processes.py)
def render_scenario(scenario: Scenario, folder: Path, seed: int | None = None,
                    progress: Callable[[str, int, int], None] | None = None) -> int:
    """Write the image folder; returns the number of images."""
    seed = scenario.seed if seed is None else seed
    config = scenario.render
    if progress is not None:
        progress("terrain", 0, 1)
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), seed), seed=seed)
    traverse, truth = maps_of_rendered_ground(scenario, *simulate(scenario, seed), seed, renderer)
    rig = traverse.rig
    calibration = raw_stereo_pair(rig.wac, rig.baseline_m, config)
    left_camera, right_camera, left_T_right = as_built(calibration, truth.kinds.get("stereo_calibration"))
    rng = np.random.default_rng([seed, 3])
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)

    def shoot(name: str, world_T_camera: np.ndarray, camera: Camera) -> str:
        image = sensor_image(renderer.render(world_T_camera, camera), rng, config.sensor_noise_dn)
        if not cv2.imwrite(str(folder / name), image):
            raise ResultsError(f"{folder / name}: cannot write the image (disk full or no permission?)")
        return name

    def stereo(prefix: str, world_T_left: np.ndarray) -> tuple[str, str]:
        return (shoot(f"{prefix}_left.png", world_T_left, left_camera),
                shoot(f"{prefix}_right.png", world_T_left @ left_T_right, right_camera))

    total = len(traverse.stops) + (_panorama_count(traverse) if config.panoramas else 0)
    done = 0
    frames, panorama = [], []
    for stop, world_T_body in zip(traverse.stops, truth.world_T_body, strict=True):
        k = stop.index
        frames.append(stereo(f"images/{k:06d}", world_T_body @ traverse.body_T_nav().matrix()))
        done += 1
        if config.panoramas:
            # each frame taken at the mast's true angles and named by its readings
            pointed = iter(truth.mast_angles.get(k, ()))
            for f in stop.panorama:
                world_T_left = world_T_body @ rig.body_T_left(*next(pointed, (f.pan_rad, f.tilt_rad))).matrix()
                left, right = stereo(_frame_name(stop.site_id, "wac", f.pan_rad, f.tilt_rad), world_T_left)
                panorama.append(PanoramaImage(k, stop.site_id, "wac", f.pan_rad, f.tilt_rad, left, right))
                done += 1
            for f in stop.hrc:
                name = _frame_name(stop.site_id, "hrc", f.pan_rad, f.tilt_rad) + ".png"
                world_T_hrc = world_T_body @ rig.body_T_hrc(*next(pointed, (f.pan_rad, f.tilt_rad))).matrix()
                shoot(name, world_T_hrc, rig.hrc)
                panorama.append(PanoramaImage(k, stop.site_id, "hrc", f.pan_rad, f.tilt_rad, name))
                done += 1
        if progress is not None:
            progress("rendering", done, total)
    # The scenario's own VO error model: on these renders white pixel noise holds over the run
    # and KITTI's rotation floor made the covariance ten times too wide (docs/frontend.md,
    # "Leave one out").
    write_observations(folder, traverse, scenario.estimator, seed, truth, scenario.rig, frames=frames,
                       panorama_frames=panorama, calibration=calibration)
    return 2 * len(frames) + sum(2 if p.camera == "wac" else 1 for p in panorama)


def as_built(calibration: StereoCalibration, drawn: dict[str, float] | None
              ) -> tuple[Camera, Camera, np.ndarray]:
    """The left and right cameras and the right one's pose in the left one's frame as the pair
    really is: the calibration's, off by the stereo calibration error the simulation drew
    (`drawn`, the truth's stereo_calibration state; None: none), which the folder's calibration
    does not say. The errors are the rectified pair's; put on the raw pair, whose axes are a
    fraction of a degree from the rectified ones, they are the same to second order."""
    left, right = calibration.cameras()
    left_T_right = calibration.left_T_right()
    if drawn is None:
        return left, right, left_T_right
    common = 1.0 + drawn["focal_scale"]
    right_scale = common * (1.0 + drawn["right_focal_ratio"])
    left = replace(left, fx=left.fx * common, fy=left.fy * common)
    right = replace(right, fx=right.fx * right_scale, fy=right.fy * right_scale)
    turn = gtsam.Rot3.Expmap(np.array([drawn[f"right_rotation_{axis}_rad"] for axis in "xyz"])).matrix()
    true_T = left_T_right.copy()
    true_T[:3, :3] = turn @ left_T_right[:3, :3]
    true_T[:3, 3] = left_T_right[:3, 3] * (1.0 + drawn["baseline_scale"])
    return left, right, true_T


def maps_of_rendered_ground(scenario: Scenario, traverse: Traverse, truth: GroundTruth, seed: int,
                            renderer: TerrainRenderer | None = None) -> tuple[Traverse, GroundTruth]:
    """The traverse with its orbital maps made of the ground the images show (the renderer's,
    which is not the measurement-level simulation's landmark terrain), drawn from the same
    stream as the simulation's: the same georeference error. With the `renderer`, the
    orthoimage is that ground rendered from above under the orbiter's sun, albedo and rocks
    and all; without, the DTM's hillshade. Unchanged without maps."""
    if Orbital.name not in traverse.measurements:
        return traverse, truth
    ground = Ground(scenario, dense_path(scenario.path), seed)
    truth = replace(truth, terrain=ground.height)
    maps, state = Orbital.simulate_with_truth(scenario.orbital, traverse, truth, kind_rng(seed, Orbital.name))
    if renderer is not None:
        bias = MapBias(state["map0_east_m"], state["map0_north_m"], state["map0_rotation_rad"])
        heights = (float(truth.positions[:, 2].min()) - 50.0, float(truth.positions[:, 2].max()) + 50.0)
        rng = np.random.default_rng([seed, 13])
        maps = tuple(replace(m, orthoimage=rendered_orthoimage(renderer, m.orthoimage, traverse.origin, bias,
                                                                scenario.orbital, heights, rng))
                     if m.orthoimage is not None else m for m in maps)
    return (replace(traverse, measurements={**traverse.measurements, Orbital.name: maps}),
            replace(truth, kinds={**truth.kinds, Orbital.name: state}))


ORTHO_CHUNK_PX = 1024  # rendered a square of this many pixels at a time
ORTHO_NOISE_DN = 2.0


def rendered_orthoimage(renderer: TerrainRenderer, raster: MapRaster, frame: LocalFrame, bias: MapBias,
                        sensor: OrbitalSensor, heights_m: tuple[float, float], rng: np.random.Generator
                        ) -> MapRaster:
    """`raster`'s pixels rendered from above: the ground the map (with its `bias`) puts under
    each, lit by the orbiter's sun, with sensor noise. 0 where there is no rendered ground (the
    corridor around the path ends). The map projection is taken as affine over each chunk of
    ORTHO_CHUNK_PX (512 m at 0.5 m: at most 6 mm off on Mars at 18 deg north), at the origin's height
    (a map point's horizontal ENU moves with its height: at 1 km from the origin on Mars, 0.3 mm
    per metre)."""
    crs = CRS.from_wkt(raster.crs_wkt)
    rows, cols = raster.values.shape
    out = np.zeros((rows, cols), np.uint8)
    px = raster.post_m
    for r0 in range(0, rows, ORTHO_CHUNK_PX):
        for c0 in range(0, cols, ORTHO_CHUNK_PX):
            h, w = min(ORTHO_CHUNK_PX, rows - r0), min(ORTHO_CHUNK_PX, cols - c0)
            corner = (raster.x0_m + c0 * px, raster.y0_m - r0 * px)
            gx, gy = np.meshgrid(corner[0] + np.linspace(0, w * px, 3), corner[1] - np.linspace(0, h * px, 3))
            map_xy = np.column_stack([gx.ravel(), gy.ravel()])
            true = bias.from_map(frame.from_map(map_xy, frame.h0_m, crs)[:, :2])
            map_T_world = np.linalg.lstsq(np.column_stack([true, np.ones(len(true))]), map_xy, rcond=None)[0].T
            image = renderer.render_top_down(map_T_world, corner, px, (w, h), sensor.sun_azimuth_deg,
                                             sensor.sun_elevation_deg, heights_m)
            seen = np.isfinite(image)
            dn = np.clip(np.rint(np.nan_to_num(image) * 255.0 + rng.normal(0.0, ORTHO_NOISE_DN, image.shape)), 1, 255)
            out[r0:r0 + h, c0:c0 + w] = np.where(seen, dn, 0).astype(np.uint8)
    return replace(raster, values=out)


def _frame_name(site: int, camera: str, pan_rad: float, tilt_rad: float) -> str:
    return f"images/site{site:03d}_{camera}_pan{np.rad2deg(pan_rad):+07.1f}_tilt{np.rad2deg(tilt_rad):+05.1f}"


def _panorama_count(traverse: Traverse) -> int:
    return sum(len(s.panorama) + len(s.hrc) for s in traverse.stops)
