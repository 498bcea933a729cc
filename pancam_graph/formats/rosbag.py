"""ROS1 and ROS2 bags through the `rosbags` package: GPS fixes, wheel odometry, camera images
and stereo camera_info. (No IMU reader: nothing reads a bag's IMU yet; the one that was, with
its test on the real Husky bag, is in git history before the commit that removed it.)"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry.stereo_pair import RectifiedStereo
from ..records import GpsFix, OdometryTrack
from .calibration import rectified_from_projections

NAVSAT_NO_FIX = -1  # sensor_msgs/NavSatStatus.STATUS_NO_FIX


def _messages(path: Path, topic: str | None, msgtype_suffix: str):
    """Yield (index, stamp seconds, message) of one topic (None: the bag's only topic of that
    type); every failure names file and topic."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such bag")
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as reader:
            if topic is None:
                typed = sorted({c.topic for c in reader.connections if c.msgtype.endswith(msgtype_suffix)})
                if len(typed) != 1:
                    raise InputError(f"{path}: {len(typed)} {msgtype_suffix} topics ({', '.join(typed) or 'none'}); "
                                     "choose one on the command line")
                topic = typed[0]
            connections = [c for c in reader.connections if c.topic == topic]
            if not connections:
                topics = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections)
                raise InputError(f"{path}: no topic {topic}; the bag has {topics}")
            if not connections[0].msgtype.endswith(msgtype_suffix):
                raise InputError(f"{path}: topic {topic} is {connections[0].msgtype}, expected {msgtype_suffix}")
            for i, (conn, _, raw) in enumerate(reader.messages(connections=connections)):
                msg = reader.deserialize(raw, conn.msgtype)
                yield i, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, msg
    except InputError:
        raise
    except Exception as exc:  # rosbags raises several types for truncated or corrupt files
        raise InputError(f"{path}: cannot read topic {topic}: {type(exc).__name__}: {exc}") from None


def read_navsatfix(path: Path, topic: str | None, min_sigma_m: float = 0.1) -> tuple[list[GpsFix], list[str]]:
    """`sensor_msgs/NavSatFix` messages as fixes, and the reasons for each rejected one.

    Height: the message defines `altitude` as ellipsoidal, and that is what this reader assumes
    (many drivers put height above mean sea level there: a constant offset of tens of metres,
    harmless to horizontal results). Sigmas come from the diagonal of `position_covariance`
    (ENU); fixes without a covariance are rejected."""
    fixes, rejected = [], []
    for i, t, m in _messages(path, topic, "NavSatFix"):
        where = f"{path}: {topic} message {i}"
        if m.status.status == NAVSAT_NO_FIX:
            rejected.append(f"{where}: status NO_FIX")
            continue
        cov = np.asarray(m.position_covariance, dtype=float).reshape(3, 3)
        if m.position_covariance_type == 0 or not np.all(np.isfinite(cov)) or cov[0, 0] <= 0:
            rejected.append(f"{where}: no position covariance")
            continue
        if not (np.isfinite(m.latitude) and np.isfinite(m.longitude) and np.isfinite(m.altitude)):
            rejected.append(f"{where}: non-finite position")
            continue
        sigma_h = max(float(np.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))), min_sigma_m)
        sigma_v = max(float(np.sqrt(cov[2, 2])), min_sigma_m)
        fixes.append(GpsFix(t, float(m.latitude), float(m.longitude), float(m.altitude), sigma_h, sigma_v))
    return fixes, rejected


def read_odometry(path: Path, topic: str | None) -> OdometryTrack:
    """`nav_msgs/Odometry` poses (the integrated wheel odometry of the robot's driver)."""
    times, poses = [], []
    for _, t, m in _messages(path, topic, "Odometry"):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        poses.append(gtsam.Pose3(gtsam.Rot3.Quaternion(q.w, q.x, q.y, q.z), np.array([p.x, p.y, p.z])).matrix())
        times.append(t)
    if len(times) < 2:
        raise InputError(f"{path}: topic {topic} has {len(times)} odometry messages; need at least 2")
    times = np.asarray(times)
    if np.any(np.diff(times) < 0):
        order = np.argsort(times, kind="stable")
        times, poses = times[order], [poses[i] for i in order]
    return OdometryTrack(f"{path}:{topic or 'Odometry'}", times, np.stack(poses))


@dataclass(frozen=True)
class StampedImage:
    time_s: float
    image: np.ndarray  # (H, W) grayscale or (H, W, 3) BGR, the bag's bit depth


# sensor_msgs/Image encodings: (numpy dtype, channels, OpenCV conversion to BGR or None)
_IMAGE_ENCODINGS = {
    "mono8": (np.uint8, 1, None), "8UC1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None), "16UC1": (np.uint16, 1, None),
    "bgr8": (np.uint8, 3, None), "8UC3": (np.uint8, 3, None),
    "rgb8": (np.uint8, 3, "COLOR_RGB2BGR"),
    "bgra8": (np.uint8, 4, "COLOR_BGRA2BGR"), "rgba8": (np.uint8, 4, "COLOR_RGBA2BGR"),
}


def read_images(path: Path, topic: str | None) -> Iterator[StampedImage]:
    """Images of one topic (None: the bag's only image topic), `sensor_msgs/Image` or
    `sensor_msgs/CompressedImage`, decoded one at a time so a long bag never sits in memory."""
    topic, kind = _image_topic(path, topic)
    for i, t, m in _messages(path, topic, kind):
        where = f"{path}: {topic} message {i}"
        yield StampedImage(t, _compressed(m, where) if kind == "CompressedImage" else _raw_image(m, where))


def _image_topic(path: Path, topic: str | None) -> tuple[str, str]:
    """The topic and its kind, 'Image' or 'CompressedImage'."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such bag")
    try:
        with AnyReader([path]) as reader:
            types = {c.topic: c.msgtype.rsplit("/", 1)[-1] for c in reader.connections}
    except Exception as exc:  # rosbags raises several types for truncated or corrupt files
        raise InputError(f"{path}: cannot read: {type(exc).__name__}: {exc}") from None
    images = sorted(t for t, kind in types.items() if kind in ("Image", "CompressedImage"))
    if topic is None:
        if len(images) != 1:
            raise InputError(f"{path}: {len(images)} image topics ({', '.join(images) or 'none'}); "
                             "choose one on the command line")
        topic = images[0]
    if topic not in images:
        have = ", ".join(f"{t} ({kind})" for t, kind in sorted(types.items()))
        raise InputError(f"{path}: topic {topic} is not an Image or CompressedImage topic; the bag has {have}")
    return topic, types[topic]


def _raw_image(m, where: str) -> np.ndarray:
    import cv2

    if m.encoding not in _IMAGE_ENCODINGS:
        raise InputError(f"{where}: image encoding '{m.encoding}' is not supported "
                         f"(supported: {', '.join(_IMAGE_ENCODINGS)})")
    dtype, channels, conversion = _IMAGE_ENCODINGS[m.encoding]
    itemsize = np.dtype(dtype).itemsize
    row = m.width * channels * itemsize
    if m.step < row or len(m.data) < m.step * m.height:
        raise InputError(f"{where}: {m.width}x{m.height} {m.encoding} needs {m.step} x {m.height} bytes "
                         f"(step >= {row}); the message has {len(m.data)}")
    rows = np.asarray(m.data, dtype=np.uint8)[: m.step * m.height].reshape(m.height, m.step)[:, :row]
    image = rows.copy().view(np.dtype(dtype).newbyteorder(">" if m.is_bigendian else "<"))
    image = image.astype(dtype).reshape((m.height, m.width) if channels == 1 else (m.height, m.width, channels))
    return cv2.cvtColor(image, getattr(cv2, conversion)) if conversion else image


def _compressed(m, where: str) -> np.ndarray:
    import cv2

    image = cv2.imdecode(np.asarray(m.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{where}: format '{m.format}': the data do not decode as an image")
    return image


def read_stereo_camera_info(path: Path, left_topic: str, right_topic: str) -> RectifiedStereo:
    """The rectified stereo model from the first `sensor_msgs/CameraInfo` of the left and right
    topics (their projection matrices P, the right one carrying Tx = -fx * baseline)."""
    infos = []
    for topic in (left_topic, right_topic):
        first = next(iter(_messages(path, topic, "CameraInfo")), None)
        if first is None:
            raise InputError(f"{path}: topic {topic} has no CameraInfo messages")
        m = first[2]
        projection = np.asarray(m.P if hasattr(m, "P") else m.p, dtype=float)  # ROS1 P, ROS2 p
        if projection.size != 12 or not np.all(np.isfinite(projection)) or projection[0] <= 0:
            raise InputError(f"{path}: {topic} message 0: P must be 12 finite numbers with fx > 0, "
                             f"got {projection.tolist()}")
        infos.append((projection.reshape(3, 4), (int(m.width), int(m.height))))
    (p_left, size), (p_right, _) = infos
    return rectified_from_projections(p_left, p_right, size, (f"{path}: {left_topic}", f"{path}: {right_topic}"))
