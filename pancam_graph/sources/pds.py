"""A folder of Mars rover image products (PDS3 labels: formats/pds.py) as a traverse: one stop per
(site, drive) of the rover motion counter, in time order; the rover's onboard poses chained
through the site frames into one east-north-up frame at the first site; their increments and
tilts the onboard kind's measurements (kinds/onboard.py). An MSLICE locations file in the folder
(formats/mslice.py) places the first site on Mars and scores the estimate at every drive it
has: held-out positions, never in a graph.

Left-only products (no stereo partner for any image) run without VO and say so once; stereo
from rover products (CAHVOR pairs resampled to linear ones) is not built yet."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import EstimatorConfig, SourceOptions
from ..errors import InputError
from ..formats.mslice import find_mslice_file, read_mslice_locations
from ..formats.pds import BODY_R_ROVER, LABEL_SUFFIXES, RoverImage, enu_T_body, read_rover_images, site_origins
from ..geometry.cahvor import to_photogrammetric
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Rig
from ..kinds.onboard import OnboardSettings, OnboardTilt, step_covariance
from ..records import DeadReckoning, GpsFix, SlipPrior, StereoObservations, Stop, Traverse
from ..solve.results import SourceInfo
from .registry import Source, SourceData

NAVCAM_BASELINE_M = 0.424  # MSL Navcam stereo baseline (Maki et al. 2012); the products here give no partner
PAIR_TOLERANCE_S = 1.0  # a left and a right image of one instrument this close in time are a stereo pair
# MSLICE states no accuracy for its positions: what the held-out score's "stated" figure assumes
MSLICE_SIGMA_M = 1.0
CONFIGURATIONS = {"onboard": ["onboard"]}


def matches(path: Path) -> bool:
    """A folder with PDS3 labels in it or one level down (one folder a sol, as archives have them)."""
    if not path.is_dir():
        return False
    return any(p.suffix in LABEL_SUFFIXES for pattern in ("*", "*/*") for p in path.glob(pattern))


def stops_of(images: list[RoverImage]) -> list[list[RoverImage]]:
    """The images grouped by stop: a run of images with one (site, drive) is one stop."""
    groups: list[list[RoverImage]] = []
    for image in images:
        if groups and (groups[-1][0].site, groups[-1][0].drive) == (image.site, image.drive):
            groups[-1].append(image)
        else:
            groups.append([image])
    return groups


def stereo_pairs(images: list[RoverImage]) -> int:
    """How many left images have a right partner (same instrument pair, within PAIR_TOLERANCE_S)."""
    rights = sorted(i.utc_s for i in images if i.eye == "RIGHT")
    lefts = [i.utc_s for i in images if i.eye == "LEFT"]
    if not rights:
        return 0
    at = np.searchsorted(rights, lefts)
    near = [min(abs(t - rights[j]) for j in (k - 1, k) if 0 <= j < len(rights)) for t, k in zip(lefts, at, strict=True)]
    return int(np.sum(np.array(near) <= PAIR_TOLERANCE_S))


def load(folder: Path, progress: Callable[[str, int, int], None] | None = None) -> SourceData:
    folder = Path(folder)
    images = read_rover_images(folder)
    groups = stops_of(images)
    if len(groups) < 2:
        raise InputError(f"{folder}: the products show the rover at one stop only (site {images[0].site}, drive "
                         f"{images[0].drive}): a traverse needs two")
    origins = site_origins(images)
    poses = [enu_T_body(group[0], origins) for group in groups]
    settings = OnboardSettings()
    stops = []
    for k, (group, pose) in enumerate(zip(groups, poses, strict=True)):
        step = None
        if k > 0:
            prev_T_curr = np.linalg.inv(poses[k - 1]) @ pose
            step = DeadReckoning(prev_T_curr, step_covariance(prev_T_curr, settings))
        stops.append(Stop(k, group[0].utc_s, StereoObservations.empty(), dead_reckoning=step,
                          dwell_s=group[-1].utc_s - group[0].utc_s))
    tilts = tuple(OnboardTilt(k, pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])) for k, pose in enumerate(poses))

    notes = []
    pairs = stereo_pairs(images)
    if pairs == 0:
        notes.append(f"left images only ({len(images)} products, no stereo partner): the stereo VO cannot run; the "
                     "onboard estimate carries the motion")
    else:
        notes.append(f"{pairs} stereo pairs: VO from rover products (CAHVOR pairs resampled to linear) is not built "
                     "yet; the onboard estimate carries the motion")
    first_site = groups[0][0].site_index
    origin, held_out, georeferenced = LocalFrame(0.0, 0.0, 0.0, body="mars"), (), False
    mslice_file = find_mslice_file(folder)
    if mslice_file is None:
        notes.append("no MSLICE locations file (mslice_locations*.xml): the frame is not placed on Mars, and "
                     "nothing scores the estimate")
    else:
        mslice = read_mslice_locations(mslice_file)
        anchor = mslice.get((first_site, 0))
        if anchor is None:
            notes.append(f"{mslice_file.name} has no position of site {first_site}'s origin (site {first_site}, "
                         "drive 0): the frame is not placed on Mars")
        else:
            origin, georeferenced = LocalFrame(anchor.lat_deg, anchor.lon_deg, 0.0, body="mars"), True
            held_out = tuple(
                GpsFix(stop.time_s, m.lat_deg, m.lon_deg, 0.0, MSLICE_SIGMA_M, 1e3)
                for stop, group in zip(stops, groups, strict=True)
                if (m := mslice.get((group[0].site, group[0].drive))) is not None)
            notes.append(f"{mslice_file.name}: site {first_site}'s origin placed at {anchor.lat_deg:.6f}, "
                         f"{anchor.lon_deg:.6f} (planetocentric); {len(held_out)} of {len(stops)} stops scored "
                         f"against its ground-updated positions (held out; MSLICE states no accuracy, "
                         f"{MSLICE_SIGMA_M:g} m assumed)")

    first = groups[0][0]
    camera = to_photogrammetric(first.camera, first.width, first.height)
    body_T_nav_left = np.eye(4)
    body_T_nav_left[:3, :3] = BODY_R_ROVER @ camera.model_R_camera
    body_T_nav_left[:3, 3] = BODY_R_ROVER @ camera.centre
    traverse = Traverse(
        name=folder.name, rig=Rig(f"{first.instrument} (CAHVOR of {first.label.name})", camera.camera,
                                  NAVCAM_BASELINE_M, mast_height_m=float(-camera.centre[2])),
        origin=origin, stops=tuple(stops), traverse_tilt_rad=0.0, image_noise_px=0.5,
        gps_lever_arm_m=np.zeros(3), start_world_T_body=poses[0],
        start_sigmas=np.array([1e-4] * 3 + [1e-3] * 3),
        # the increments' error is their covariance (kinds/onboard.py), not a slip of the wheels'
        wheel_slip=SlipPrior(0.0, 1e-6), body_T_nav_left=body_T_nav_left,
        measurements={"onboard": tilts})
    info = SourceInfo("pds", str(folder), "MSLICE ground-updated positions (held out)" if held_out else "none",
                      notes=tuple(notes), georeferenced=georeferenced,
                      stop_counters=tuple((group[0].site, group[0].drive) for group in groups))
    return SourceData(traverse, None, EstimatorConfig(configurations=CONFIGURATIONS), 0, info, held_out=held_out)


def _load(text: str, options: SourceOptions, progress) -> SourceData:
    return load(Path(text), progress)


SOURCES = (Source("pds", 45, frozenset(), matches, _load,
                  "a folder of rover image products with PDS3 labels (*.LBL)"),)
