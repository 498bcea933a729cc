"""A folder of Mars rover image products (PDS3 labels: formats/pds.py; PDS4: formats/pds4.py) as a
traverse: one stop per (site, drive) of the rover motion counter, in time order; the rover's
onboard poses chained through the site frames into one east-north-up frame at the first site;
their increments and tilts the onboard kind's measurements (kinds/onboard.py). An MSLICE
locations file in the folder (formats/mslice.py) places the first site on Mars and scores the
estimate at every drive it has: held-out positions, never in a graph.

Where every stop has a stereo pair (a left and a right image of one camera pair, within
PAIR_TOLERANCE_S), the pair's CAHVOR models become the photogrammetric pair they are within
their conversion's residual (geometry/cahvor.py), OpenCV rectifies it to a linear epipolar
pair, and the image front-end tracks it as it does an image folder's: the `vo` configuration
runs beside `onboard`. Left-only products run without VO and say so once."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..config import EstimatorConfig, FrontendConfig, SourceOptions
from ..errors import InputError
from ..formats import pds4
from ..formats.images import read_gray
from ..formats.mslice import find_mslice_file, read_mslice_locations
from ..formats.pds import BODY_R_ROVER, LABEL_SUFFIXES, RoverImage, enu_T_body, read_rover_images, site_origins
from ..frontend.tracker import StereoTracker
from ..geometry.cahvor import to_photogrammetric
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Rig
from ..geometry.stereo_pair import StereoCalibration
from ..kinds.onboard import OnboardSettings, OnboardTilt, step_covariance
from ..records import DeadReckoning, GpsFix, SlipPrior, StereoObservations, Stop, Traverse
from ..solve.results import SourceInfo
from .frames import median_frame_ms, odometry_camera_motion, track_frames
from .registry import Source, SourceData, frontend_for

NAVCAM_BASELINE_M = 0.424  # MSL Navcam stereo baseline (Maki et al. 2012), for products that give no partner
# Matching and localisation error (1 sigma) of features tracked on rectified images: what the
# front-end measured on KITTI's real frames (formats/kitti.py); a label states none
FEATURE_SIGMA_PX = 0.5
PAIR_TOLERANCE_S = 1.0  # a left and a right image of one instrument this close in time are a stereo pair
# MSLICE states no accuracy for its positions: what the held-out score's "stated" figure assumes
MSLICE_SIGMA_M = 1.0
CONFIGURATIONS = {"onboard": ["onboard"]}


def matches(path: Path) -> bool:
    """A folder with PDS3 or PDS4 labels in it or one level down (one folder a sol, as archives
    have them)."""
    if not path.is_dir():
        return False
    return any(p.suffix in LABEL_SUFFIXES or pds4.is_label(p) for pattern in ("*", "*/*") for p in path.glob(pattern))


def stops_of(images: list[RoverImage]) -> list[list[RoverImage]]:
    """The images grouped by stop: a run of images with one (site, drive) is one stop."""
    groups: list[list[RoverImage]] = []
    for image in images:
        if groups and (groups[-1][0].site, groups[-1][0].drive) == (image.site, image.drive):
            groups[-1].append(image)
        else:
            groups.append([image])
    return groups


def stereo_pairs(images: list[RoverImage]) -> list[tuple[RoverImage, RoverImage]]:
    """Each left image with its right partner: the image of the same camera pair (the instrument
    with RIGHT for LEFT in its name) nearest in time, within PAIR_TOLERANCE_S."""
    rights: dict[str, list[RoverImage]] = {}
    for image in images:
        if image.eye == "RIGHT":
            rights.setdefault(image.instrument.replace("RIGHT", "LEFT"), []).append(image)
    pairs = []
    for left in (i for i in images if i.eye == "LEFT"):
        partner = min(rights.get(left.instrument, []), key=lambda r: abs(r.utc_s - left.utc_s), default=None)
        if partner is not None and abs(partner.utc_s - left.utc_s) <= PAIR_TOLERANCE_S:
            pairs.append((left, partner))
    return pairs


def read_product_image(image: RoverImage) -> np.ndarray:
    """A product's 8-bit grey image: a PDS4 product's raw array, or a PDS3 label's browse image."""
    if image.image is None:
        raise InputError(f"{image.label}: no image beside the label")
    if image.label.suffix == pds4.LABEL_SUFFIX:
        return pds4.read_image(image)
    if image.image.suffix.lower() == ".img":
        raise InputError(f"{image.image}: PDS3 .IMG pixels are not read yet; give the browse images (.jpg, .png)")
    return read_gray(image.image, (image.height, image.width), f"its label {image.label.name}")


@dataclass(frozen=True)
class ProductStereo:
    """A CAHVOR pair as the front-end takes it: the photogrammetric pair it converts to (OpenCV's
    calibration and rectification), and the raw left camera in the rover body frame."""

    calibration: StereoCalibration
    body_T_raw_left: np.ndarray
    residual_px: float  # the largest of the two conversions' residuals over the image


SAME_POINTING_M, SAME_POINTING_DEG = 1e-3, 0.01  # camera models this close are one mounting


def pointing_change(stop_pairs: list[tuple[RoverImage, RoverImage]]) -> int | None:
    """The first stop whose pair differs from the first stop's: camera models (centre and axis,
    either eye) by more than SAME_POINTING_M or SAME_POINTING_DEG, or images of another size
    (a downsampled frame); None when every pair is the first's."""
    reference = stop_pairs[0]
    for k, pair in enumerate(stop_pairs):
        for a, b in zip(reference, pair, strict=True):
            angle = np.rad2deg(np.arccos(np.clip(a.camera.a @ b.camera.a, -1.0, 1.0)))
            if (np.linalg.norm(a.camera.c - b.camera.c) > SAME_POINTING_M or angle > SAME_POINTING_DEG
                    or (a.width, a.height) != (b.width, b.height)):
                return k
    return None


def product_stereo(left: RoverImage, right: RoverImage) -> ProductStereo:
    converted = [to_photogrammetric(image.camera, image.width, image.height) for image in (left, right)]
    rover_T = []
    for photo in converted:
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = photo.model_R_camera, photo.centre
        rover_T.append(pose)
    right_T_left = np.linalg.inv(rover_T[1]) @ rover_T[0]
    (a, b) = (photo.camera for photo in converted)
    calibration = StereoCalibration(f"{left.label.name} + {right.label.name}", a.matrix(), a.distortion(),
                                    b.matrix(), b.distortion(), (left.width, left.height), right_T_left[:3, :3],
                                    right_T_left[:3, 3])
    body_T_raw_left = np.eye(4)
    body_T_raw_left[:3, :3] = BODY_R_ROVER @ rover_T[0][:3, :3]
    body_T_raw_left[:3, 3] = BODY_R_ROVER @ rover_T[0][:3, 3]
    return ProductStereo(calibration, body_T_raw_left, max(photo.residual_px for photo in converted))


def load(folder: Path, progress: Callable[[str, int, int], None] | None = None,
         frontend: FrontendConfig | None = None, skip_bad_frames: bool = False) -> SourceData:
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
    paired = {(left.site, left.drive): (left, right) for left, right in reversed(pairs)}  # a stop's first pair
    stop_pairs = [paired.get((group[0].site, group[0].drive)) for group in groups]
    if not pairs:
        notes.append(f"left images only ({len(images)} products, no stereo partner): the stereo VO cannot run; the "
                     "onboard estimate carries the motion")
    elif None in stop_pairs:
        missing = stop_pairs.index(None)
        notes.append(f"{len(pairs)} stereo pairs, but stop {missing} (site {groups[missing][0].site}, drive "
                     f"{groups[missing][0].drive}) has none: the stereo VO needs a pair at every stop; the onboard "
                     "estimate carries the motion")
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
    paired_everywhere = bool(pairs) and None not in stop_pairs
    moved = pointing_change(stop_pairs) if paired_everywhere else None
    if moved is not None:
        notes.append(f"{len(pairs)} stereo pairs, but the pair's camera models or image sizes change at stop "
                     f"{moved} (the mast pointed elsewhere, or another frame size): the stereo VO needs one camera "
                     "pair as mounted; the onboard estimate carries the motion")
    stereo = product_stereo(*stop_pairs[0]) if paired_everywhere and moved is None else None
    if stereo is None:
        camera = to_photogrammetric(first.camera, first.width, first.height)
        body_T_nav_left = np.eye(4)
        body_T_nav_left[:3, :3] = BODY_R_ROVER @ camera.model_R_camera
        body_T_nav_left[:3, 3] = BODY_R_ROVER @ camera.centre
        rig = Rig(f"{first.instrument} (CAHVOR of {first.label.name})", camera.camera, NAVCAM_BASELINE_M,
                  mast_height_m=float(-camera.centre[2]))
    else:
        rectified = stereo.calibration.rectified()
        body_T_nav_left = stereo.body_T_raw_left.copy()
        body_T_nav_left[:3, :3] = body_T_nav_left[:3, :3] @ rectified.raw_R_rectified
        rig = Rig(f"{first.instrument} pair (CAHVOR of {stereo.calibration.source}, rectified)", rectified.camera,
                  rectified.baseline_m, mast_height_m=float(body_T_nav_left[2, 3]),
                  raw_R_rectified=tuple(rectified.raw_R_rectified.ravel().tolist()))
        notes.append(f"{len(pairs)} stereo pairs: CAHVOR to photogrammetric within {stereo.residual_px:.2g} px, "
                     f"rectified by OpenCV to a linear pair (baseline {rectified.baseline_m:.3f} m)")
    traverse = Traverse(
        name=folder.name, rig=rig, origin=origin, stops=tuple(stops), traverse_tilt_rad=0.0,
        image_noise_px=FEATURE_SIGMA_PX, gps_lever_arm_m=np.zeros(3), start_world_T_body=poses[0],
        start_sigmas=np.array([1e-4] * 3 + [1e-3] * 3),
        # the increments' error is their covariance (kinds/onboard.py), not a slip of the wheels'
        wheel_slip=SlipPrior(0.0, 1e-6), body_T_nav_left=body_T_nav_left,
        measurements={"onboard": tilts})
    info = SourceInfo("pds", str(folder), "MSLICE ground-updated positions (held out)" if held_out else "none",
                      notes=tuple(notes), georeferenced=georeferenced,
                      stop_counters=tuple((group[0].site, group[0].drive) for group in groups))
    configurations = dict(CONFIGURATIONS, **({"vo": ["vo"]} if stereo is not None else {}))
    data = SourceData(traverse, None, EstimatorConfig(configurations=configurations), 0, info, held_out=held_out)
    if stereo is None:
        return data
    return tracked(data, stop_pairs, stereo, frontend or FrontendConfig(), skip_bad_frames, progress)


def tracked(data: SourceData, stop_pairs: list[tuple[RoverImage, RoverImage]], stereo: ProductStereo,
            frontend: FrontendConfig, skip_bad_frames: bool,
            progress: Callable[[str, int, int], None] | None) -> SourceData:
    """The traverse's stops with the image front-end's tracks of their stereo pairs (rectified)."""
    tracker = StereoTracker(frontend)
    rectify = stereo.calibration.rectification_maps()

    def read_pair(k: int) -> tuple[np.ndarray, np.ndarray]:
        pair = tuple(read_product_image(image) for image in stop_pairs[k])
        start = time.perf_counter()
        rectified = rectify(*pair)
        tracker.times.add("rectify", start)
        return rectified

    def finish(stops: list[Stop], notes: list[str]) -> SourceData:
        n = len(stops)
        info = replace(data.info, notes=(*data.info.notes, f"front-end {frontend.detector}: median "
                                         f"{median_frame_ms(tracker):.1f} ms per frame", *notes),
                       options={"detector": frontend.detector, "skip_bad_frames": skip_bad_frames})
        return replace(data, traverse=replace(data.traverse, stops=tuple(stops)), info=info,
                       held_out=tuple(f for f in data.held_out if f.time_s <= stops[-1].time_s) if n else ())

    camera_motion = odometry_camera_motion(data.traverse) if frontend.odometry_aided else None
    return track_frames(data.traverse.stops, read_pair, tracker, finish, skip_bad_frames, progress, camera_motion)


def _load(text: str, options: SourceOptions, progress) -> SourceData:
    return load(Path(text), progress, frontend_for(options), bool(options.skip_bad_frames))


SOURCES = (Source("pds", 45, frozenset({"detector", "skip_bad_frames"}), matches, _load,
                  "a folder of rover image products (PDS3 *.LBL or PDS4 *.xml labels)"),)
