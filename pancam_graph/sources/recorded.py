"""Recorded drives without stereo observations (a ROS bag's wheel odometry and NavSatFix, a KITTI
raw drive's OXTS) as traverses: one stop at each GPS fix time, the odometry between consecutive
fixes as a dead-reckoning increment with a distance-based covariance, every `holdout_every`-th
fix kept out of the graph to score the result against measurements it never saw."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import gtsam
import numpy as np

from ..config import EstimatorConfig, SourceOptions
from ..errors import InputError
from ..evaluation.metrics import fit_yaw
from ..evaluation.timed import poses_at_times
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import rig_preset
from ..records import DeadReckoning, GpsFix, GroundTruth, OdometryTrack, SlipPrior, StereoObservations, Stop, Traverse
from ..solve.results import SourceInfo
from .registry import Source, SourceData, frontend_for

_ALIGN_DISTANCE_M = 15.0  # odometry travelled before the initial heading is taken from GPS


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel odometry error model (1 sigma). A driver's own odometry covariance is usually a
    constant placeholder, so the model is set here: translation error grows with distance
    (slip), heading error as a random walk in distance plus a fraction of each turn."""

    translation_fraction: float = 0.05
    min_translation_m: float = 0.02
    heading_deg_per_sqrt_m: float = 0.5
    turn_fraction: float = 0.05
    min_heading_deg: float = 0.05
    tilt_deg: float = 1.0  # roll and pitch per step: wheel odometry assumes flat ground
    vertical_fraction: float = 0.1

    def covariance(self, prev_T_curr: gtsam.Pose3) -> np.ndarray:
        d = float(np.linalg.norm(prev_T_curr.translation()))
        turn = abs(prev_T_curr.rotation().yaw())
        yaw = max(np.deg2rad(self.heading_deg_per_sqrt_m) * np.sqrt(d) + self.turn_fraction * turn,
                  np.deg2rad(self.min_heading_deg))
        xy = max(self.translation_fraction * d, self.min_translation_m)
        z = max(self.vertical_fraction * d, self.min_translation_m)
        tilt = np.deg2rad(self.tilt_deg)
        return np.diag(np.array([tilt, tilt, yaw, xy, xy, z]) ** 2)


def odometry_at(track: OdometryTrack, times_s: np.ndarray) -> list[gtsam.Pose3]:
    """Odometry poses interpolated on SE(3) (geodesic between the bracketing messages) at the given times."""
    idx = np.clip(np.searchsorted(track.times_s, times_s), 1, len(track) - 1)
    poses = []
    for t, j in zip(times_s, idx, strict=True):
        t0, t1 = track.times_s[j - 1], track.times_s[j]
        a = 0.0 if t1 == t0 else float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
        poses.append(gtsam.Pose3(track.odom_T_body[j - 1]).slerp(a, gtsam.Pose3(track.odom_T_body[j])))
    return poses


def drive_traverse(name: str, source: str, odometry: OdometryTrack, fixes: list[GpsFix], holdout_every: int,
                   noise: OdometryNoise = OdometryNoise()) -> tuple[Traverse, tuple[GpsFix, ...]]:
    """The traverse (stops at the fix times) and the held-out fixes."""
    fixes = sorted((f for f in fixes if odometry.times_s[0] <= f.time_s <= odometry.times_s[-1]),
                   key=lambda f: f.time_s)
    if len(fixes) < 3:
        raise InputError(f"{source}: only {len(fixes)} GPS fixes fall inside the odometry's time span")
    origin = LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].h_m)
    times = np.array([f.time_s for f in fixes])
    if np.any(np.diff(times) <= 0):
        raise InputError(f"{source}: two GPS fixes share the time {times[np.argmin(np.diff(times))]:.6f} s")
    enu = origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.h_m for f in fixes])
    used = np.ones(len(fixes), dtype=bool)
    if holdout_every > 0:
        used[holdout_every - 1:: holdout_every] = False

    odom = odometry_at(odometry, times)
    world_T_odom = _initial_alignment(np.array([p.translation() for p in odom]), enu, used)
    stops = []
    for i, t in enumerate(times):
        dr = None
        if i > 0:
            step = odom[i - 1].between(odom[i])
            dr = DeadReckoning(step.matrix(), noise.covariance(step))
        stops.append(Stop(i, float(t), StereoObservations.empty(), dead_reckoning=dr))
    sigma_h, sigma_v = fixes[0].sigma_horizontal_m, fixes[0].sigma_vertical_m
    traverse = Traverse(
        name=name, rig=rig_preset("exomars"), origin=origin, stops=tuple(stops), traverse_tilt_rad=0.0,
        image_noise_px=0.3, gps_lever_arm_m=np.zeros(3),
        start_world_T_body=world_T_odom @ odom[0].matrix(),
        start_sigmas=np.array([np.deg2rad(5.0), np.deg2rad(5.0), np.deg2rad(30.0), 3 * sigma_h, 3 * sigma_h,
                               3 * sigma_v]),
        measurements={"gps": tuple(f for f, u in zip(fixes, used, strict=True) if u)},
        # wheel odometry calibrated by its driver: no expected slip, a few percent either way
        wheel_slip=SlipPrior(0.0, noise.translation_fraction),
    )
    return traverse, tuple(f for f, u in zip(fixes, used, strict=True) if not u)


def _initial_alignment(odom_xyz: np.ndarray, enu: np.ndarray, used: np.ndarray) -> np.ndarray:
    """world_T_odom (4x4) from the first stretch of drive: heading is unobservable before the
    robot has moved, so it is fitted to the used fixes over the first ~15 m."""
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(odom_xyz, axis=0), axis=1))])
    n = int(np.searchsorted(travelled, _ALIGN_DISTANCE_M)) + 1
    first = used.copy()
    first[n:] = False
    if first.sum() < 3:
        first = used
    rot, t = fit_yaw(odom_xyz[first], enu[first])
    world_T_odom = np.eye(4)
    world_T_odom[:3, :3], world_T_odom[:3, 3] = rot, t
    return world_T_odom


def is_bag(path: Path) -> bool:
    path = Path(path)
    return (path.is_file() and path.suffix in (".bag", ".db3", ".mcap")) or (path / "metadata.yaml").is_file()


def is_kitti_drive(path: Path) -> bool:
    return (Path(path) / "oxts" / "timestamps.txt").is_file()


def load_bag(path: Path, gps_topic: str | None = None, odom_topic: str | None = None,
             holdout_every: int = 5) -> SourceData:
    """Topics left as None are the bag's only NavSatFix / Odometry topic."""
    from ..formats.rosbag import read_navsatfix, read_odometry

    fixes, rejected = read_navsatfix(path, gps_topic)
    if not fixes:
        raise InputError(f"{path}: no usable GPS fixes ({len(rejected)} rejected)")
    odometry = read_odometry(path, odom_topic)
    traverse, held_out = drive_traverse(Path(path).stem, str(path), odometry, fixes, holdout_every)
    info = SourceInfo("rosbag", str(path), "none", notes=(
        f"{gps_topic or 'NavSatFix'}: altitude taken as ellipsoidal height",
        f"{odom_topic or 'Odometry'}: wheel odometry with the distance-based noise model "
        "(the driver's covariance is not used)",
        "stops at the GPS fix times; odometry interpolated on SE(3) to them"),
        options={"gps_topic": gps_topic, "odom_topic": odom_topic, "holdout_every": holdout_every})
    return SourceData(traverse, None, EstimatorConfig(), 0, info, held_out=held_out, rejected=tuple(rejected))


def load_kitti_raw(folder: Path, geoid_height_m: float = 0.0, holdout_every: int = 5) -> SourceData:
    from ..formats.kitti import read_kitti_raw

    drive = read_kitti_raw(folder)
    odometry = drive.velocity_odometry()
    traverse, held_out = drive_traverse(Path(folder).name, str(folder), odometry, drive.gps_fixes(geoid_height_m),
                                        holdout_every)
    reference = drive.world_T_body(traverse.origin, geoid_height_m)  # at the odometry (OXTS packet) times
    stop_times = np.array([s.time_s for s in traverse.stops])
    truth = GroundTruth(poses_at_times(odometry.times_s, odometry.times_s, reference, stop_times), np.zeros((0, 3)))
    info = SourceInfo("kitti_raw", str(folder), "OXTS poses (GPS/IMU solution)", notes=(
        "odometry: OXTS body velocities and rates integrated packet to packet",
        f"GPS: OXTS positions, height = alt + {geoid_height_m} m geoid height, "
        "sigma = pos_accuracy horizontally, twice that vertically"),
        options={"geoid_height_m": geoid_height_m, "holdout_every": holdout_every})
    return SourceData(traverse, truth, EstimatorConfig(), 0, info, held_out=held_out)


_PAIR_TOLERANCE_S = 0.005  # a left and a right image this close in time are one stereo pair


def load_stereo_bag(path: Path, left_topic: str, right_topic: str, left_info: str, right_info: str,
                    frontend=None, progress=None, skip_bad_frames: bool = False) -> SourceData:
    """A bag with a rectified stereo pair (Image or CompressedImage) and its two CameraInfo
    topics: one stop per stereo pair, the image front-end over every pair, a body-fixed camera
    (left camera at the body origin looking forward). GPS fixes and wheel odometry, when the
    bag has them, come along: fixes at their own times, odometry interpolated to the pairs."""
    from ..formats.rosbag import read_images, read_navsatfix, read_odometry, read_stereo_camera_info
    from ..frontend.tracker import StereoTracker
    from ..geometry.rig import BODY_T_FORWARD_CAMERA, Rig
    from .frames import track_frames

    stereo = read_stereo_camera_info(path, left_info, right_info)
    cam = stereo.camera
    rights = [(m.time_s, m.image) for m in read_images(path, right_topic)]
    right_times = np.array([t for t, _ in rights])
    pairs = []  # (time, left image, right image)
    unpaired = 0
    for message in read_images(path, left_topic):
        j = int(np.argmin(np.abs(right_times - message.time_s))) if len(right_times) else -1
        if j < 0 or abs(right_times[j] - message.time_s) > _PAIR_TOLERANCE_S:
            unpaired += 1
            continue
        pairs.append((message.time_s, message.image, rights[j][1]))
    if len(pairs) < 2:
        raise InputError(f"{path}: {len(pairs)} stereo pairs on {left_topic} + {right_topic} (within "
                         f"{_PAIR_TOLERANCE_S * 1e3:.0f} ms; {unpaired} left images without a right one)")

    def read_pair(k: int) -> tuple[np.ndarray, np.ndarray]:
        time_s, left, right = pairs[k]
        left, right = _gray(left), _gray(right)
        for topic, image in ((left_topic, left), (right_topic, right)):
            if image.shape != (cam.height, cam.width):
                raise InputError(f"{path}: {topic} at t = {time_s:.3f} s: {image.shape[1]} x "
                                 f"{image.shape[0]} px, but the camera_info says {cam.width} x {cam.height}")
        return left, right

    fixes, odometry = [], None
    try:
        fixes, _ = read_navsatfix(path, None)
    except InputError:
        pass  # no (single) NavSatFix topic: a VO-only bag
    try:
        odometry = read_odometry(path, None)
    except InputError:
        pass
    from .kitti_odometry import REAL_IMAGE_ESTIMATOR

    def finish(stops: list[Stop], notes: list[str]) -> SourceData:
        if odometry is not None:
            odom = odometry_at(odometry, np.array([s.time_s for s in stops]))
            stops = [stop if k == 0 else replace(stop, dead_reckoning=DeadReckoning(
                odom[k - 1].between(odom[k]).matrix(), OdometryNoise().covariance(odom[k - 1].between(odom[k]))))
                for k, stop in enumerate(stops)]
        origin = LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].h_m) if fixes else LocalFrame(0.0, 0.0, 0.0)
        traverse = Traverse(
            name=Path(path).stem, rig=Rig(Path(path).stem, cam, stereo.baseline_m, mast_height_m=1.0),
            origin=origin, stops=tuple(stops), traverse_tilt_rad=0.0, image_noise_px=0.5,
            gps_lever_arm_m=np.zeros(3), start_world_T_body=np.eye(4), start_sigmas=np.array([1e-4] * 3 + [1e-3] * 3),
            measurements={"gps": tuple(sorted(fixes, key=lambda f: f.time_s))}, body_T_nav_left=BODY_T_FORWARD_CAMERA)
        placed = ("the start pose is the local frame's origin (the bag gives no surveyed start)" if fixes else
                  "no GPS fix in the bag: the local frame has no geodetic origin, so no geographic file (WGS84 "
                  "CSV, GeoJSON, KML) is written")
        info = SourceInfo("rosbag", str(path), "none", notes=(
            f"stereo pairs from {left_topic} + {right_topic} ({unpaired} unpaired left images)", placed, *notes),
            options={"stereo_topics": (left_topic, right_topic)}, georeferenced=bool(fixes))
        return SourceData(traverse, None, REAL_IMAGE_ESTIMATOR, 0, info)

    stops = [Stop(k, time_s, StereoObservations.empty()) for k, (time_s, _, _) in enumerate(pairs)]
    return track_frames(stops, read_pair, StereoTracker(frontend), finish, skip_bad_frames, progress)


def _gray(image: np.ndarray) -> np.ndarray:
    import cv2

    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
    return image


def _load_bag(text: str, options: SourceOptions, progress) -> SourceData:
    """A bag's GPS and odometry, or with stereo_topics its images through the front-end."""
    holdout = 5 if options.holdout_every is None else options.holdout_every
    if options.stereo_topics is None:
        options.check("rosbag", {"gps_topic", "odom_topic", "holdout_every"})
        return load_bag(Path(text), options.gps_topic, options.odom_topic, holdout)
    options.check("rosbag", {"stereo_topics", "detector", "skip_bad_frames"})
    left, right = options.stereo_topics
    frontend = frontend_for(options)
    return load_stereo_bag(Path(text), left, right, _info_topic(left), _info_topic(right), frontend, progress,
                           bool(options.skip_bad_frames))


def _info_topic(image_topic: str) -> str:
    """The CameraInfo topic beside an image topic: /left/image_rect[/compressed] -> /left/camera_info."""
    parts = [p for p in image_topic.split("/") if p and p != "compressed"]
    return "/" + "/".join(parts[:-1] + ["camera_info"])


def _load_kitti_raw(text: str, options: SourceOptions, progress) -> SourceData:
    holdout = 5 if options.holdout_every is None else options.holdout_every
    return load_kitti_raw(Path(text), options.geoid_height_m or 0.0, holdout)


SOURCES = (
    Source("rosbag", 10, frozenset({"gps_topic", "odom_topic", "holdout_every", "stereo_topics", "detector",
                                    "skip_bad_frames"}), is_bag, _load_bag,
           "a ROS1 bag or a ROS2 bag folder (metadata.yaml)"),
    Source("kitti_raw", 20, frozenset({"geoid_height_m", "holdout_every"}), is_kitti_drive, _load_kitti_raw,
           "a KITTI raw drive folder (oxts/)", estimator=lambda text: EstimatorConfig()),
)
