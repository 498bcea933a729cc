"""KITTI odometry sequence 00 as GTSAM's Python wheel ships it (`gtsam.findExampleDataFile`):
real stereo tracks of its first 154 frames, their rectified calibration, the drive's real GPS
in a local metric frame, and the example's own VO poses.

    VO_stereo_factors00.txt   frame track u_left u_right v X Y Z      (one row per observation)
    VO_calibration00.txt      fx fy skew cx cy baseline_m
    VO_camera_poses00.txt     frame, then the left camera's 4x4 pose row by row (first = identity)
    KittiGps_converted.txt    Time,X,Y,Z   (header; s of day, local metres, Z up)

Frames 93-131 come every other frame (the example left the rest out); the GPS covers the whole
drive (4541 frames, 470.9 s) at 1 Hz. The files carry no frame times and no antenna offset; the
antenna is KITTI's OXTS unit at its calibrated place on the car (`OXTS_IN_CAMERA_BODY_M`).
With KITTI's ground truth of the sequence (`read_kitti00_truth`: poses and times of every
frame) the frames get the truth's times, and the clock offset and the truth's place in the
GPS's frame are fitted on every fix of the drive (`fit_start_on_truth`, `kitti00_on_truth`).
Without it, the frame times are the GPS span cut into 4540 equal steps, and the start and the
clock are fitted on the example's VO poses (`fit_start`). Neither fit ever sees an estimate this
project makes, so a run of these tracks is judged on a reference it was not fitted to.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import BODY_T_FORWARD_CAMERA, Camera, Rig
from ..records import GpsFix, GroundTruth, SlipPrior, StereoObservations, Stop, Traverse
from ..runtime.text_files import read_text
from .kitti import FEATURE_SIGMA_PX
from .tables import CsvTable

GPS_COLUMNS = ["Time", "X", "Y", "Z"]
FILES = ("VO_stereo_factors00.txt", "VO_calibration00.txt", "VO_camera_poses00.txt", "KittiGps_converted.txt")
TRUTH_POSES = ("poses.txt", "poses.txt.gz")
# KITTI's ground truth of sequence 00 steps exactly 0.860 m per frame (to a millimetre) over
# frames 0-15, while the car accelerates there: the example's VO and ours both measure 0.68 m
# rising to 0.86 m, and agree to 2 mm a step; from frame 16 on all three agree (0.996 of the
# truth's length). The truth is judged trustworthy from this frame (docs/frontend.md).
TRUTH_FIRST_FRAME = 16
IMAGE_SIZE = (1241, 376)  # KITTI sequence 00, rectified grayscale (width, height)
SEQUENCE_FRAMES = 4541  # sequence 00 = raw drive 2011_10_03_0027, which the GPS file covers
# The OXTS unit (whose position the GPS file holds) from the left grey camera, body axes (x forward,
# y left, z up), from KITTI's calib_imu_to_velo and calib_velo_to_cam: 1.08 m behind the camera,
# 0.32 m left, 0.73 m below (the 2011_09_26 calibration in ../shared/data/real/kitti_raw; the car's
# later calibrations move it by about 2 cm).
OXTS_IN_CAMERA_BODY_M = (-1.082, 0.322, -0.727)
# The GPS file's local frame has no published origin; only differences matter. A nominal one
# where the drive was (Karlsruhe), so the WGS84 exports land near it.
NOMINAL_ORIGIN = LocalFrame(49.0, 8.4, 110.0)
# The fixes' 1-sigma per horizontal axis and vertically: OXTS RTK as the drive logged it, 0.37 m
# 2-D RMS against the sequence's ground truth over the whole drive once the clock and the antenna
# are right (`fit_start_on_truth`). Over a few tens of seconds the error is a bias more than
# noise (0.2-0.3 m, one sign), which these white sigmas do not describe (docs/frontend.md).
GPS_SIGMA_HORIZONTAL_M = 0.25
GPS_SIGMA_VERTICAL_M = 0.5


@dataclass(frozen=True)
class Kitti00Example:
    """The four files, read."""

    frames: np.ndarray  # (N,) KITTI frame numbers with tracks, increasing
    observations: tuple[StereoObservations, ...]  # per frame
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    example_world_T_camera: np.ndarray  # (N, 4, 4) the example's VO poses of the left camera
    gps_times_s: np.ndarray  # (M,)
    gps_xyz_m: np.ndarray  # (M, 3) local metres, z up

    @property
    def frame_step_s(self) -> float:
        """Time between frames: the GPS span over the sequence's frames."""
        return float(self.gps_times_s[-1] - self.gps_times_s[0]) / (SEQUENCE_FRAMES - 1)

    def frame_times_s(self, clock_offset_s: float = 0.0) -> np.ndarray:
        """Each frame's time on the GPS clock."""
        return self.gps_times_s[0] + clock_offset_s + self.frames * self.frame_step_s

    def from_frame(self, first: int) -> Kitti00Example:
        """The example from KITTI frame `first` on."""
        keep = self.frames >= first
        if keep.sum() < 2:
            raise InputError(f"frames from {first}: fewer than two of the example's frames")
        return replace(self, frames=self.frames[keep],
                       observations=tuple(o for o, k in zip(self.observations, keep, strict=True) if k),
                       example_world_T_camera=self.example_world_T_camera[keep])


def example_data_folder() -> Path:
    """Where the installed gtsam wheel keeps its example data."""
    try:
        return Path(gtsam.findExampleDataFile(FILES[0])).parent
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"gtsam's example data: {FILES[0]} not found ({exc}); is gtsam installed "
                         "from the wheel?") from None


def read_kitti00_example(folder: Path | None = None) -> Kitti00Example:
    """The example's files from `folder` (default: the installed wheel's data folder)."""
    folder = example_data_folder() if folder is None else Path(folder)
    tracks_path, calibration_path, poses_path, gps_path = (folder / name for name in FILES)
    rows, lines = _numbers(tracks_path, 8)
    rows[:, 0] = _ids(tracks_path, lines, rows[:, 0], "frame")
    rows[:, 1] = _ids(tracks_path, lines, rows[:, 1], "track")
    frames = np.unique(rows[:, 0].astype(np.int64))
    observations = []
    for f in frames:
        mine = rows[rows[:, 0] == f]
        tracks = mine[:, 1].astype(np.int64)
        if len(np.unique(tracks)) != len(tracks):
            raise InputError(f"{tracks_path}: frame {f} lists a track twice")
        observations.append(StereoObservations(tracks, mine[:, 2:5].copy()))
    calibration, _ = _numbers(calibration_path, 6)
    if len(calibration) != 1:
        raise InputError(f"{calibration_path}: expected one row (fx fy skew cx cy baseline), got {len(calibration)}")
    fx, fy, _, cx, cy, baseline = calibration[0]
    poses, lines = _numbers(poses_path, 17)
    if not np.array_equal(_ids(poses_path, lines, poses[:, 0], "frame"), frames):
        raise InputError(f"{poses_path}: its frames are not those of {tracks_path.name}")
    gps = _gps(gps_path)
    return Kitti00Example(frames, tuple(observations), float(fx), float(fy), float(cx), float(cy), float(baseline),
                          poses[:, 1:].reshape(-1, 4, 4), gps[:, 0], gps[:, 1:])


def _numbers(path: Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Whitespace-separated numbers, `columns` per line, and each row's line number."""
    rows, lines = [], []
    for line, text in enumerate(read_text(path).splitlines(), start=1):
        fields = text.split()
        if not fields:
            continue
        if len(fields) != columns:
            raise InputError(f"{path}: line {line}: expected {columns} numbers, got {len(fields)}")
        try:
            rows.append([float(v) for v in fields])
        except ValueError:
            raise InputError(f"{path}: line {line}: expected numbers, got {text.strip()[:60]!r}") from None
        lines.append(line)
    if not rows:
        raise InputError(f"{path}: no rows")
    array = np.array(rows)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        raise InputError(f"{path}: line {lines[int(np.flatnonzero(~finite)[0])]}: non-finite number")
    return array, np.array(lines)


def _ids(path: Path, lines: np.ndarray, values: np.ndarray, what: str) -> np.ndarray:
    """A column of frame or track numbers: whole numbers in 0..2^53."""
    good = (values >= 0) & (values < 2.0**53) & (values == np.floor(values))
    if not good.all():
        bad = int(np.flatnonzero(~good)[0])
        raise InputError(f"{path}: line {lines[bad]}: {what} {float(values[bad])!r}: expected a whole number from 0")
    return values.astype(np.int64)


def _gps(path: Path) -> np.ndarray:
    table = CsvTable(path, GPS_COLUMNS)
    rows = []
    for line, row in table.rows:
        rows.append([table.number(line, column, text) for column, text in zip(GPS_COLUMNS, table.values(line, row),
                                                                               strict=True)])
        if len(rows) > 1 and rows[-1][0] <= rows[-2][0]:
            raise InputError(f"{path}: line {line}: time {rows[-1][0]} does not increase")
    if len(rows) < 2:
        raise InputError(f"{path}: fewer than two fixes")
    return np.array(rows)


@dataclass(frozen=True)
class StartFit:
    """Where the car started on the GPS's local frame, fitted on the example's VO poses: the
    similarity (yaw, translation, scale) and clock offset that best lay the OXTS unit of those
    poses onto the fixes of the frames' span. Only the start pose and the clock offset are kept:
    the scale and the residuals describe the example's VO, not the drive."""

    world_T_body: np.ndarray  # 4x4, the first frame's body (x forward, y left, z up) in the local frame
    clock_offset_s: float
    scale: float  # of the example's VO against the GPS (1 when fitted on the truth)
    sigmas: np.ndarray  # (6,) 1-sigma [roll, pitch, yaw rad, x, y, z m] of the start pose
    rms_m: float  # horizontal RMS of the fit's residuals
    fixes: int
    frame_times_s: np.ndarray  # (N,) the example's frames on the GPS clock
    truth_world_T_body: np.ndarray | None = None  # (N, 4, 4) the frames' true poses, when fitted on the truth


@dataclass(frozen=True)
class _TrackFit:
    """Camera poses' OXTS track laid onto GPS fixes: the parameters (x[0] the clock offset), their
    1-sigma, the horizontal RMS of the residuals and the poses as body poses."""

    x: np.ndarray
    std: np.ndarray
    rms_m: float
    body: np.ndarray  # (N, 4, 4)


def _fit_track_to_fixes(world_T_camera: np.ndarray, times: np.ndarray, fix_t: np.ndarray, fix_xyz: np.ndarray,
                        place, x0: np.ndarray, **options) -> _TrackFit:
    """Least squares of `place(x, antenna)` (the antenna at the fixes' times, clock-shifted by
    x[0], moved into the GPS's frame) onto the fixes; the covariance scaled by the residuals."""
    from scipy.optimize import least_squares

    body = BODY_T_FORWARD_CAMERA @ world_T_camera @ np.linalg.inv(BODY_T_FORWARD_CAMERA)
    antenna = body[:, :3, 3] + body[:, :3, :3] @ np.asarray(OXTS_IN_CAMERA_BODY_M)

    def predicted(x: np.ndarray) -> np.ndarray:
        return place(x, np.column_stack([np.interp(fix_t - x[0], times, antenna[:, i]) for i in range(3)]))

    fit = least_squares(lambda x: (predicted(x) - fix_xyz).ravel(), x0, **options)
    residual = predicted(fit.x) - fix_xyz
    dof = max(residual.size - len(fit.x), 1)
    covariance = np.linalg.pinv(fit.jac.T @ fit.jac) * float(np.sum(residual**2)) / dof
    return _TrackFit(fit.x, np.sqrt(np.diag(covariance)),
                     float(np.sqrt(np.mean(np.sum(residual[:, :2] ** 2, axis=1)))), body)


def fit_start(example: Kitti00Example) -> StartFit:
    """The start pose and clock offset from the example's VO poses and the GPS (least squares)."""
    times = example.frame_times_s()
    # fixes from half a second before the first frame: the clock offset may move them in
    inside = (example.gps_times_s >= times[0] - 0.5) & (example.gps_times_s <= times[-1])
    fix_t, fix_xyz = example.gps_times_s[inside], example.gps_xyz_m[inside]
    start_yaw = np.arctan2(*(fix_xyz[-1, 1::-1] - fix_xyz[0, 1::-1]))  # roughly along the drive
    # x: clock offset, yaw, translation (3), log of the example VO's scale
    fit = _fit_track_to_fixes(example.example_world_T_camera, times, fix_t, fix_xyz,
                              lambda x, at: np.exp(x[5]) * at @ _yaw(x[1]).T + x[2:5],
                              np.r_[0.0, start_yaw, fix_xyz[0], 0.0])
    world_T_body = np.eye(4)
    world_T_body[:3, :3] = _yaw(fit.x[1])
    world_T_body[:3, 3] = fit.x[2:5]
    horizontal = max(fit.std[2], fit.std[3])
    level = np.deg2rad(1.0)  # the car's roll and pitch at the start: level to a degree
    return StartFit(world_T_body, float(fit.x[0]), float(np.exp(fit.x[5])),
                    np.array([level, level, fit.std[1], horizontal, horizontal, fit.std[4]]), fit.rms_m,
                    int(inside.sum()), example.frame_times_s(float(fit.x[0])))


@dataclass(frozen=True)
class Kitti00Truth:
    """KITTI's ground truth of sequence 00 (the benchmark's poses/00.txt and times.txt): every
    frame's time from the first and its left camera's pose in the first frame's camera frame."""

    times_s: np.ndarray  # (4541,)
    world_T_camera: np.ndarray  # (4541, 4, 4)


def read_kitti00_truth(folder: Path) -> Kitti00Truth:
    """`poses.txt` (or `poses.txt.gz`: KITTI's 12 numbers per frame) and `times.txt` of `folder`."""
    folder = Path(folder)
    poses_path = next((folder / n for n in TRUTH_POSES if (folder / n).exists()), folder / TRUTH_POSES[0])
    poses, _ = _numbers(poses_path, 12)
    times_path = folder / "times.txt"
    times, lines = _numbers(times_path, 1)
    for path, count in ((poses_path, len(poses)), (times_path, len(times))):
        if count != SEQUENCE_FRAMES:
            raise InputError(f"{path}: {count} frames; sequence 00 has {SEQUENCE_FRAMES}")
    step = np.diff(times[:, 0])
    if not (step > 0).all():
        raise InputError(f"{times_path}: line {lines[int(np.flatnonzero(step <= 0)[0]) + 1]}: time does not increase")
    world_T_camera = np.tile(np.eye(4), (len(poses), 1, 1))
    world_T_camera[:, :3, :] = poses.reshape(-1, 3, 4)
    return Kitti00Truth(times[:, 0], world_T_camera)


def fit_start_on_truth(example: Kitti00Example, truth: Kitti00Truth) -> StartFit:
    """The start pose and clock offset from KITTI's ground truth: the rigid motion and clock
    offset that best lay the truth's OXTS track onto every fix of the drive (robust least
    squares; 469 fixes over 4541 frames). The example's frames then get the truth's own times and
    poses, carried into the GPS's frame; `scale` is 1 (the truth is metric)."""
    from scipy.spatial.transform import Rotation

    times = example.gps_times_s[0] + truth.times_s
    inside = (example.gps_times_s >= times[0]) & (example.gps_times_s <= times[-1])
    fix_t, fix_xyz = example.gps_times_s[inside], example.gps_xyz_m[inside]
    ahead = min(10, len(fix_xyz) - 1)
    start_yaw = np.arctan2(*(fix_xyz[ahead, 1::-1] - fix_xyz[0, 1::-1]))  # roughly along the first 10 s
    # x: clock offset, rotation vector (3), translation (3)
    fit = _fit_track_to_fixes(truth.world_T_camera, times, fix_t, fix_xyz,
                              lambda x, at: at @ Rotation.from_rotvec(x[1:4]).as_matrix().T + x[4:7],
                              np.r_[0.0, 0.0, 0.0, start_yaw, fix_xyz[0]], loss="soft_l1", f_scale=1.0)
    gps_T_truth = np.eye(4)
    gps_T_truth[:3, :3] = Rotation.from_rotvec(fit.x[1:4]).as_matrix()
    gps_T_truth[:3, 3] = fit.x[4:7]
    frames_world_T_body = gps_T_truth @ fit.body[example.frames]
    # the start's sigma: the fit's, on the rotation (rotvec, about the same small angles) and
    # the translation, the truth's frame 0 being where the car was
    return StartFit(frames_world_T_body[0], float(fit.x[0]), 1.0, fit.std[1:7], fit.rms_m, int(inside.sum()),
                    times[example.frames] + float(fit.x[0]), frames_world_T_body)


def _yaw(angle: float) -> np.ndarray:
    return gtsam.Rot3.Yaw(float(angle)).matrix()


def kitti00_traverse(example: Kitti00Example, start: StartFit) -> Traverse:
    """The example's frames as the stops of a traverse (numbered 0..N-1 in frame order, at their
    times on the GPS clock) with the fixes of their span, the car's stereo pair fixed to its body
    and the start pose of `start`."""
    times = start.frame_times_s
    stops = tuple(Stop(k, float(t), obs) for k, (t, obs) in enumerate(zip(times, example.observations, strict=True)))
    during = (example.gps_times_s >= times[0]) & (example.gps_times_s <= times[-1])
    geodetic = NOMINAL_ORIGIN.to_geodetic(example.gps_xyz_m[during])
    fixes = tuple(GpsFix(float(t), float(lat), float(lon), float(h), GPS_SIGMA_HORIZONTAL_M, GPS_SIGMA_VERTICAL_M)
                  for t, (lat, lon, h) in zip(example.gps_times_s[during], geodetic, strict=True))
    camera = Camera(example.fx, example.fy, example.cx, example.cy, *IMAGE_SIZE)
    return Traverse(
        name="kitti00_gtsam", rig=Rig("kitti 00", camera, example.baseline_m, mast_height_m=1.65),
        origin=NOMINAL_ORIGIN, stops=stops, traverse_tilt_rad=0.0, image_noise_px=FEATURE_SIGMA_PX,
        gps_lever_arm_m=np.array(OXTS_IN_CAMERA_BODY_M), start_world_T_body=start.world_T_body,
        start_sigmas=start.sigmas, wheel_slip=SlipPrior(), body_T_nav_left=BODY_T_FORWARD_CAMERA,
        measurements={"gps": fixes},
    )


def kitti00_on_truth(example: Kitti00Example, truth: Kitti00Truth) -> tuple[Traverse, GroundTruth, StartFit]:
    """The example's frames from TRUTH_FIRST_FRAME on, at the truth's times, starting where the
    truth says, with the frames' true poses in the GPS's frame."""
    example = example.from_frame(TRUTH_FIRST_FRAME)
    start = fit_start_on_truth(example, truth)
    return kitti00_traverse(example, start), GroundTruth(start.truth_world_T_body, np.zeros((0, 3))), start
