"""An image folder's navigation stereo pairs as rover image products in PDS4 (formats/pds4.py),
as a rover would send them down: each image with its time, the rover motion counter, the
camera as a CAHVOR model in the rover navigation frame (the lens's radial distortion as its R
terms) and the rover's onboard pose (the dead-reckoned one: odometry.csv chained from the
start) in a site frame; and, for Mars, an MSLICE-style file placing them on the planet. A new
site frame is declared at each site of the traverse, its origin where the rover is then, as
the missions do. `pancam-graph run` on the products goes through the same front-end as on
the folder (sources/pds.py).

The site panoramas are not written (their pointing would need the mast's articulation in the
labels and a rig model to use it)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import Scenario
from ..errors import InputError
from ..formats.images import read_gray
from ..formats.mslice import MsliceLocation, write_mslice_locations
from ..formats.pds import BODY_R_ROVER, ENU_R_SITE, site_T_rover
from ..formats.pds4 import ProductDescription, write_product
from ..geometry.cahvor import from_photogrammetric
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera
from ..kinds.sun_heading import start_utc_s
from ..store.observation_folder import read_observations

MISSION = "PANCAM_GRAPH SIMULATION"
# Where the products are on Mars, as MSLICE has it for a mission: site 1's origin (the traverse's
# origin) and, when the folder has its truth, the rover's true place at every drive: the
# ground-updated positions the PDS source scores the run against, never feeds it
MSLICE_FILE = "mslice_locations_simulated.xml"


def _rover_camera(camera: Camera, body_T_camera: np.ndarray, name: str):
    """The camera's CAHVOR model in the rover navigation frame (x forward, y right, z down)."""
    return from_photogrammetric(camera, BODY_R_ROVER @ body_T_camera[:3, :3], BODY_R_ROVER @ body_T_camera[:3, 3],
                                name)


def onboard_poses(stops, start_world_T_body: np.ndarray, folder: Path) -> list[np.ndarray]:
    """The rover's dead-reckoned pose at each stop, east-north-up: the start chained with the odometry."""
    poses = [np.asarray(start_world_T_body, dtype=float)]
    for stop in stops[1:]:
        if stop.dead_reckoning is None:
            raise InputError(f"{folder}: stop {stop.index} has no odometry (odometry.csv): a rover product needs "
                             "the onboard pose at every image")
        poses.append(poses[-1] @ stop.dead_reckoning.prev_T_curr)
    return poses


def scenario_start_utc_s(scenario: Scenario) -> float:
    """The scenario's time 0 in UTC: its sun's start (kinds/sun_heading.py), which every scenario has."""
    o = scenario.origin
    return start_utc_s(scenario.sun_heading, LocalFrame(o.lat_deg, o.lon_deg, o.h_m, o.body))


def write_pds4_products(image_folder: Path, out: Path, start_utc_s: float,
                        progress: Callable[[str, int, int], None] | None = None) -> int:
    """Write the navigation pairs of `image_folder` into `out` as PDS4 products; `start_utc_s`
    is the traverse's time 0 (UTC, POSIX seconds). Returns the number of products."""
    obs = read_observations(image_folder)
    traverse = obs.traverse
    if obs.frames is None:
        raise InputError(f"{image_folder}: not an image folder (no frames.csv)")
    rig = traverse.rig
    body_T_left = traverse.body_T_nav().matrix()
    if obs.calibration is None:  # a pair rectified as mounted: both cameras the rig's, side by side
        left_camera = right_camera = rig.wac
        left_T_right = np.eye(4)
        left_T_right[0, 3] = rig.baseline_m
    else:
        body_T_left[:3, :3] = body_T_left[:3, :3] @ rig.rectification().T  # the raw left camera
        left_camera, right_camera = obs.calibration.cameras()
        left_T_right = obs.calibration.left_T_right()
    cameras = {"LEFT": _rover_camera(left_camera, body_T_left, "left"),
               "RIGHT": _rover_camera(right_camera, body_T_left @ left_T_right, "right")}
    size = (left_camera.height, left_camera.width)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    site, drive, site_origin = 1, 0, np.zeros(3)  # site 1's frame is the traverse's east-north-up origin
    origin = traverse.origin.to_geodetic(np.zeros((1, 3)))[0]
    locations = [MsliceLocation(1, 0, float(origin[0]), float(origin[1]), None)]
    written = 0
    for k, (stop, pose) in enumerate(zip(traverse.stops, onboard_poses(traverse.stops, traverse.start_world_T_body,
                                                                       image_folder), strict=True)):
        north_east_down = ENU_R_SITE @ pose[:3, 3]
        new_site = None
        if k > 0 and stop.site_id is not None:
            site, drive = site + 1, 0
            new_site = north_east_down - site_origin
            site_origin = north_east_down
        elif k > 0:
            drive += 1
        if obs.truth is not None and (site, drive) != (1, 0):
            lat, lon, _ = traverse.origin.to_geodetic(obs.truth.world_T_body[k][None, :3, 3])[0]
            locations.append(MsliceLocation(site, drive, float(lat), float(lon), start_utc_s + stop.time_s))
        for eye, path in zip(("LEFT", "RIGHT"), obs.frames[k], strict=True):
            product = ProductDescription(f"WAC_{eye}_{k:06d}", start_utc_s + stop.time_s, MISSION, f"WAC_{eye}",
                                         site, drive, 0, site_T_rover(pose, site_origin), new_site, cameras[eye])
            write_product(out, product, read_gray(path, size))
            written += 1
        if progress is not None:
            progress("PDS4 products", k + 1, len(traverse.stops))
    if traverse.origin.body == "mars":  # MSLICE is Mars's; elsewhere the products are not placed
        write_mslice_locations(out / MSLICE_FILE, locations)
    return written
