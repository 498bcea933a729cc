"""What a rover image product's label says of its image, whatever its format: PDS3
(formats/pds.py) or PDS4 (formats/pds4.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.cahvor import CameraModel


@dataclass(frozen=True)
class RoverImage:
    """One image product as its label describes it."""

    label: Path
    utc_s: float
    instrument: str  # INSTRUMENT_ID, e.g. NAV_LEFT_A
    eye: str  # FRAME_ID: LEFT or RIGHT (MONO for a single camera)
    site: int
    drive: int
    pose: int
    site_T_rover: np.ndarray  # 4x4: the rover frame in its site frame (onboard, telemetry)
    site_index: int  # the site frame the pose is in
    site_origin: tuple[int, np.ndarray] | None  # (reference site, this site's origin in that site's frame)
    camera: CameraModel  # in the rover navigation frame
    width: int
    height: int
    sun_site_azimuth_deg: float | None  # clockwise from north, in the site frame (the mission's)
    sun_site_elevation_deg: float | None
    mission: str = ""  # INSTRUMENT_HOST_ID, e.g. MSL
    image: Path | None = None  # the product's image beside its label, when there is one

    @property
    def motion_counter(self) -> tuple[int, int, int]:
        return self.site, self.drive, self.pose


def frame_pose(offset: np.ndarray, quaternion: tuple[float, float, float, float], what: str) -> np.ndarray:
    """A frame's pose (4x4) in its reference frame from its origin offset and its rotation
    quaternion (s, x, y, z), as both label formats give them; `what` names the quaternion in
    the message refusing one that is not of unit length."""
    from scipy.spatial.transform import Rotation

    s, x, y, z = quaternion
    norm = float(np.sqrt(s * s + x * x + y * y + z * z))
    if abs(norm - 1.0) > 1e-3:
        raise InputError(f"{what} has length {norm:.4f}, expected a unit quaternion")
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([x, y, z, s]).as_matrix()
    out[:3, 3] = offset
    return out
