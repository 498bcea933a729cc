"""ROS1 and ROS2 bags through the `rosbags` package: GPS fixes and wheel odometry."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..records import GpsFix, OdometryTrack

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
