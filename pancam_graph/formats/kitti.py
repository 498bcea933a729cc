"""KITTI in its original folder layouts.

Raw drives: OXTS packets and timestamps, the rectified stereo calibration of the date, and the
rectified colour images when present.

    <date>/calib_cam_to_cam.txt
    <date>/<date>_drive_<NNNN>_sync/oxts/timestamps.txt, oxts/data/NNNNNNNNNN.txt
    <date>/<date>_drive_<NNNN>_sync/image_02/data/NNNNNNNNNN.png (left), image_03 (right)

Odometry sequences: rectified grayscale pairs, their times and projection matrices, and the
ground-truth poses of the left camera when published (sequences 00-10).

    <root>/sequences/<NN>/calib.txt (P0..P3, Tr), times.txt, image_0/NNNNNN.png, image_1/NNNNNN.png
    <root>/poses/<NN>.txt
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry.geodesy import LocalFrame
from ..geometry.stereo_pair import RectifiedStereo
from ..records import GpsFix, OdometryTrack
from ..runtime.text_files import read_text
from .calibration import rectified_from_projections
from .trajectories import read_kitti_poses

# Matching and localisation error (1 sigma) of features tracked on KITTI's rectified grey images:
# the image front-end's on the odometry frames, and the tracks GTSAM's wheel ships.
FEATURE_SIGMA_PX = 0.5

OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az", "af", "al", "au",
    "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode",
    "velmode", "orimode",
)


@dataclass(frozen=True)
class OxtsPackets:
    times_s: np.ndarray  # (N,) UNIX seconds
    values: np.ndarray  # (N, 30) in OXTS_FIELDS order; alt is above mean sea level (devkit)

    def field(self, name: str) -> np.ndarray:
        return self.values[:, OXTS_FIELDS.index(name)]


@dataclass(frozen=True)
class KittiDrive:
    folder: Path
    oxts: OxtsPackets
    stereo: RectifiedStereo | None
    left_images: list[Path]  # empty when the drive comes without images
    right_images: list[Path]

    def stereo_pair(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The i-th rectified pair as grayscale arrays."""
        return _grayscale(self.left_images[i]), _grayscale(self.right_images[i])

    def world_T_body(self, origin: LocalFrame, geoid_height_m: float = 0.0) -> np.ndarray:
        """OXTS poses (N, 4, 4) in `origin`'s ENU frame. The OXTS body is x forward, y left, z up
        (ours) and its yaw is counter-clockwise from east, so R = Rz(yaw) Ry(pitch) Rx(roll)
        (the devkit's convert_oxts_to_pose)."""
        o = self.oxts
        enu = origin.to_enu(o.field("lat"), o.field("lon"), o.field("alt") + geoid_height_m)
        poses = np.zeros((len(enu), 4, 4))
        for i, (roll, pitch, yaw) in enumerate(zip(o.field("roll"), o.field("pitch"), o.field("yaw"), strict=True)):
            poses[i, :3, :3] = gtsam.Rot3.Ypr(yaw, pitch, roll).matrix()
        poses[:, :3, 3], poses[:, 3, 3] = enu, 1.0
        return poses

    def velocity_odometry(self) -> OdometryTrack:
        """Dead reckoning from the OXTS body velocities (vf, vl, vu) and rates (wf, wl, wu),
        integrated on SE(3) packet to packet: what the unit's inertial side alone says."""
        o = self.oxts
        twist = np.column_stack([o.field(n) for n in ("wf", "wl", "wu", "vf", "vl", "vu")])
        pose = gtsam.Pose3()
        poses = [pose.matrix()]
        for i in range(1, len(o.times_s)):
            dt = o.times_s[i] - o.times_s[i - 1]
            pose = pose.compose(gtsam.Pose3.Expmap(0.5 * (twist[i - 1] + twist[i]) * dt))
            poses.append(pose.matrix())
        return OdometryTrack(f"{self.folder}/oxts (velocities)", o.times_s.copy(), np.stack(poses))

    def gps_fixes(self, geoid_height_m: float = 0.0, min_sigma_m: float = 0.02) -> list[GpsFix]:
        """OXTS positions as fixes: ellipsoidal height = alt + `geoid_height_m` (KITTI's alt is
        above mean sea level); horizontal sigma from pos_accuracy, vertical twice that (OXTS
        states no vertical accuracy; GNSS height is typically about twice as uncertain)."""
        accuracy = np.maximum(self.oxts.field("pos_accuracy"), min_sigma_m)
        return [GpsFix(float(t), float(lat), float(lon), float(alt) + geoid_height_m, float(s), float(2 * s))
                for t, lat, lon, alt, s in zip(self.oxts.times_s, self.oxts.field("lat"), self.oxts.field("lon"),
                                               self.oxts.field("alt"), accuracy, strict=True)]


def read_kitti_raw(drive: Path) -> KittiDrive:
    """A `<date>_drive_<NNNN>_sync` folder; the calibration is read from its parent."""
    drive = Path(drive)
    if not drive.is_dir():
        raise InputError(f"{drive}: not a KITTI raw drive folder")
    oxts = read_oxts(drive / "oxts")
    calib = drive.parent / "calib_cam_to_cam.txt"
    stereo = read_cam_to_cam(calib) if calib.exists() else None
    left = sorted((drive / "image_02" / "data").glob("*.png"))
    right = sorted((drive / "image_03" / "data").glob("*.png"))
    if len(left) != len(right):
        raise InputError(f"{drive}: {len(left)} left (image_02) but {len(right)} right (image_03) images")
    if left and len(left) != len(oxts.times_s):
        raise InputError(f"{drive}: {len(left)} stereo pairs but {len(oxts.times_s)} OXTS packets")
    return KittiDrive(drive, oxts, stereo, left, right)


def read_oxts(folder: Path) -> OxtsPackets:
    stamps_path = folder / "timestamps.txt"
    times = _read_timestamps(stamps_path)
    files = sorted((folder / "data").glob("*.txt"))
    if len(files) != len(times):
        raise InputError(f"{folder}: {len(files)} packets in data/ but {len(times)} lines in timestamps.txt")
    values = np.zeros((len(files), len(OXTS_FIELDS)))
    for i, path in enumerate(files):
        fields = read_text(path).split()
        if len(fields) != len(OXTS_FIELDS):
            raise InputError(f"{path}: line 1: expected {len(OXTS_FIELDS)} OXTS fields, got {len(fields)}")
        try:
            values[i] = [float(v) for v in fields]
        except ValueError as exc:
            raise InputError(f"{path}: line 1: {exc}") from None
        _check_packet(path, values[i])
    return OxtsPackets(times, values)


def _check_packet(path: Path, packet: np.ndarray) -> None:
    """Every field finite, a place on Earth and an accuracy that is one."""
    named = dict(zip(OXTS_FIELDS, packet, strict=True))
    for name, value in named.items():
        if not np.isfinite(value):
            raise InputError(f"{path}: line 1: {name} {value}: expected a finite number")
    for name, low, high in (("lat", -90.0, 90.0), ("lon", -180.0, 360.0)):
        if not low <= named[name] <= high:
            raise InputError(f"{path}: line 1: {name} {named[name]:g}: expected {low:g}..{high:g} degrees")
    for name in ("pos_accuracy", "vel_accuracy"):
        if named[name] < 0.0:
            raise InputError(f"{path}: line 1: {name} {named[name]:g}: expected 0 or more")


def _read_timestamps(path: Path) -> np.ndarray:
    if not path.exists():
        raise InputError(f"{path}: missing")
    times: list[float] = []
    for line, text in enumerate(read_text(path).splitlines(), start=1):
        if not text.strip():
            continue
        try:
            stamp = np.datetime64(text.strip().replace(" ", "T"), "ns")
        except ValueError:
            raise InputError(f"{path}: line {line}: expected 'YYYY-MM-DD hh:mm:ss.fffffffff', got {text!r}") from None
        t = stamp.astype(np.int64) * 1e-9
        if times and t <= times[-1]:
            raise InputError(f"{path}: line {line}: {text.strip()} does not come after the line before (timestamps "
                             "must increase)")
        times.append(t)
    return np.asarray(times)


def read_cam_to_cam(path: Path) -> RectifiedStereo:
    """Rectified cameras 02 (left) and 03 (right): P_rect_0x and S_rect_02."""
    calib = _CalibFile(path)
    width, height = calib.numbers("S_rect_02", 2)
    return rectified_from_projections(calib.numbers("P_rect_02", 12).reshape(3, 4),
                                      calib.numbers("P_rect_03", 12).reshape(3, 4), (int(width), int(height)),
                                      (f"{path}: P_rect_02", f"{path}: P_rect_03"))


@dataclass(frozen=True)
class KittiOdometrySequence:
    folder: Path
    stereo: RectifiedStereo  # cameras 0 (left) and 1 (right), grayscale
    times_s: np.ndarray  # (N,) seconds from the sequence start
    left_images: list[Path]
    right_images: list[Path]
    world_T_camera: np.ndarray | None  # (N, 4, 4) left camera (x right, y down, z forward) in the first one's frame

    def __len__(self) -> int:
        return len(self.times_s)

    def stereo_pair(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The i-th rectified pair as grayscale arrays."""
        return _grayscale(self.left_images[i]), _grayscale(self.right_images[i])


def is_kitti_odometry(folder: Path) -> bool:
    folder = Path(folder)
    return (folder / "calib.txt").is_file() and any((folder / d).is_dir() for d in ("image_0", "image_l"))


def read_kitti_odometry(sequence: Path, poses: Path | None = None, frame_period_s: float = 0.1
                        ) -> KittiOdometrySequence:
    """A KITTI odometry sequence folder: `image_0/` + `image_1/` (the benchmark's layout) or
    `image_l/` + `image_r/`, `calib.txt` with P0 and P1 (`P0: ...` lines, or the first two
    lines as bare numbers), optional `times.txt` (else one frame every `frame_period_s`), poses
    from `poses`, `poses.txt` in the folder or `<root>/poses/<NN>.txt`. The image size comes
    from the first left image."""
    sequence = Path(sequence)
    if not (sequence / "calib.txt").is_file():
        raise InputError(f"{sequence}: not a KITTI odometry sequence (no calib.txt)")
    calib = _CalibFile(sequence / "calib.txt")
    names = ("image_0", "image_1") if (sequence / "image_0").is_dir() else ("image_l", "image_r")
    left = sorted((sequence / names[0]).glob("*.png"))
    right = sorted((sequence / names[1]).glob("*.png"))
    if not left:
        raise InputError(f"{sequence / names[0]}: no PNG images")
    if [p.name for p in left] != [p.name for p in right]:
        missing = sorted({p.name for p in left} ^ {p.name for p in right})
        raise InputError(f"{sequence}: {names[0]} and {names[1]} differ: {missing[0]} is in only one of them")
    if (sequence / "times.txt").is_file():
        times = _read_seconds(sequence / "times.txt")
    else:
        times = frame_period_s * np.arange(len(left))
    if len(left) != len(times):
        raise InputError(f"{sequence / names[0]}: {len(left)} images but {len(times)} lines in times.txt")
    first = _grayscale(left[0])
    stereo = rectified_from_projections(calib.numbers("P0", 12).reshape(3, 4), calib.numbers("P1", 12).reshape(3, 4),
                                        (first.shape[1], first.shape[0]),
                                        (f"{sequence / 'calib.txt'}: P0", f"{sequence / 'calib.txt'}: P1"))
    if poses is None:
        for candidate in (sequence / "poses.txt", sequence.parent.parent / "poses" / f"{sequence.name}.txt"):
            if candidate.is_file():
                poses = candidate
                break
    world_T_camera = None
    if poses is not None:
        world_T_camera = read_kitti_poses(poses).world_T_body
        if len(world_T_camera) != len(times):
            raise InputError(f"{poses}: {len(world_T_camera)} poses but {len(times)} frames")
    return KittiOdometrySequence(sequence, stereo, times, left, right, world_T_camera)


class _CalibFile:
    """A KITTI calibration text file of `key: numbers` lines."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: missing")
        self.entries = {}
        for line, text in enumerate(read_text(self.path).splitlines(), start=1):
            key, colon, value = text.partition(":")
            if not colon and text.strip():  # bare rows of numbers: P0, P1, P2, P3 in order
                key, value = f"P{len(self.entries)}", text
            self.entries[key.strip()] = (line, value)

    def numbers(self, key: str, count: int) -> np.ndarray:
        if key not in self.entries:
            raise InputError(f"{self.path}: missing field '{key}'")
        line, value = self.entries[key]
        try:
            array = np.array([float(v) for v in value.split()])
        except ValueError:
            raise InputError(f"{self.path}: line {line}: field '{key}': expected numbers") from None
        if len(array) != count:
            raise InputError(f"{self.path}: line {line}: field '{key}': expected {count} numbers, got {len(array)}")
        return array


def _read_seconds(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: missing")
    times = []
    for line, text in enumerate(read_text(path).splitlines(), start=1):
        if text.strip():
            try:
                times.append(float(text))
            except ValueError:
                raise InputError(f"{path}: line {line}: expected seconds, got {text.strip()!r}") from None
    times = np.asarray(times)
    if np.any(np.diff(times) <= 0):
        line = int(np.argmax(np.diff(times) <= 0)) + 2
        raise InputError(f"{path}: line {line}: time does not increase")
    return times


def _grayscale(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: not a readable image")
    return image
