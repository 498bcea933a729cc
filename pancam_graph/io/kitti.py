"""KITTI raw drives in their original folder layout: OXTS packets and timestamps, the
rectified stereo calibration of the date, and the rectified colour images when present.

    <date>/calib_cam_to_cam.txt
    <date>/<date>_drive_<NNNN>_sync/oxts/timestamps.txt, oxts/data/NNNNNNNNNN.txt
    <date>/<date>_drive_<NNNN>_sync/image_02/data/NNNNNNNNNN.png (left), image_03 (right)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..geodesy import LocalFrame
from ..records import GpsFix, OdometryTrack
from ..rig import Camera
from .calibration import RectifiedStereo

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
        import cv2

        images = []
        for path in (self.left_images[i], self.right_images[i]):
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise InputError(f"{path}: not a readable image")
            images.append(image)
        return images[0], images[1]

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
        fields = path.read_text(encoding="utf-8").split()
        if len(fields) != len(OXTS_FIELDS):
            raise InputError(f"{path}: line 1: expected {len(OXTS_FIELDS)} OXTS fields, got {len(fields)}")
        try:
            values[i] = [float(v) for v in fields]
        except ValueError as exc:
            raise InputError(f"{path}: line 1: {exc}") from None
    return OxtsPackets(times, values)


def _read_timestamps(path: Path) -> np.ndarray:
    if not path.exists():
        raise InputError(f"{path}: missing")
    times = []
    for line, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not text.strip():
            continue
        try:
            stamp = np.datetime64(text.strip().replace(" ", "T"), "ns")
        except ValueError:
            raise InputError(f"{path}: line {line}: expected 'YYYY-MM-DD hh:mm:ss.fffffffff', got {text!r}") from None
        times.append(stamp.astype(np.int64) * 1e-9)
    return np.asarray(times)


def read_cam_to_cam(path: Path) -> RectifiedStereo:
    """Rectified cameras 02 (left) and 03 (right): P_rect_0x and S_rect_02."""
    entries = {}
    for line, text in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), start=1):
        key, _, value = text.partition(":")
        entries[key.strip()] = (line, value)

    def numbers(key: str, count: int) -> np.ndarray:
        if key not in entries:
            raise InputError(f"{path}: missing field '{key}'")
        line, value = entries[key]
        try:
            array = np.array([float(v) for v in value.split()])
        except ValueError:
            raise InputError(f"{path}: line {line}: field '{key}': expected numbers") from None
        if len(array) != count:
            raise InputError(f"{path}: line {line}: field '{key}': expected {count} numbers, got {len(array)}")
        return array

    left, right = numbers("P_rect_02", 12).reshape(3, 4), numbers("P_rect_03", 12).reshape(3, 4)
    width, height = numbers("S_rect_02", 2)
    camera = Camera(fx=left[0, 0], fy=left[1, 1], cx=left[0, 2], cy=left[1, 2], width=int(width), height=int(height))
    # P[0, 3] = -fx * (camera x offset from the reference camera)
    baseline = (left[0, 3] - right[0, 3]) / left[0, 0]
    return RectifiedStereo(camera, float(baseline))
