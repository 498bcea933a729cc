"""The observation folder's manifest (traverse.toml) and file layout: the file and column names,
the rig and map entries, and the checks every reader and the writer share (docs/observation_format.md)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
from pydantic import AfterValidator, Field

from ..config import EstimatorConfig, OriginConfig, _Strict

if TYPE_CHECKING:
    pass

MANIFEST = "traverse.toml"
FRAMES = "frames.csv"  # an image folder: the navigation stereo pair's images per stop
FRAME_COLUMNS = ["stop", "time_s", "dwell_s", "left", "right"]
PANORAMA_FRAMES = "panorama_frames.csv"  # an image folder: site panorama and HRC images
PANORAMA_FRAME_COLUMNS = ["stop", "site", "camera", "pan_rad", "tilt_rad", "left", "right"]
STEREO_COLUMNS = ["stop", "time_s", "track", "u_left", "u_right", "v"]
PANORAMA_COLUMNS = ["stop", "site", "pan_rad", "tilt_rad", "track", "u_left", "u_right", "v"]
HRC_COLUMNS = ["stop", "pan_rad", "tilt_rad", "track", "u", "v"]
COVARIANCE_UPPER = np.triu_indices(6)
ODOMETRY_COLUMNS = (["stop"] + [f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)] + ["tx", "ty", "tz"]
                    + [f"c{i}{j}" for i, j in zip(*COVARIANCE_UPPER, strict=True)])


LeverArm = Annotated[float, Field(ge=-10.0, le=10.0)]
Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Matrix4 = tuple[tuple[float, float, float, float], tuple[float, float, float, float],
                tuple[float, float, float, float], tuple[float, float, float, float]]
Sigma = Annotated[float, Field(gt=0.0, le=1e4)]
RIGID_TOLERANCE = 1e-6  # of R'R against identity (orthonormal axes have det +-1: its sign is checked)
MAX_TRANSLATION_M = 1e6  # as every coordinate in metres of a scenario (config.Metres)


def _rigid(matrix: Matrix4) -> Matrix4:
    """A 4x4 that is a rigid transform: a rotation (orthonormal, det +1), a translation, and
    the last row 0 0 0 1."""
    m = np.array(matrix, dtype=float)
    if not np.all(np.isfinite(m)):
        raise ValueError("not finite")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise ValueError(f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    rotation = m[:3, :3]
    if np.abs(m[:3, 3]).max() > MAX_TRANSLATION_M:
        raise ValueError(f"its translation {m[:3, 3].tolist()} lies beyond {MAX_TRANSLATION_M:g} m")
    if np.abs(rotation).max() > 1.0 + RIGID_TOLERANCE:  # and R'R would overflow on 1e308
        raise ValueError(f"its 3x3 part is not a rotation (an entry of {np.abs(rotation).max():.3g}): expected "
                         "orthonormal axes with det +1")
    off = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    with np.errstate(all="ignore"):  # subnormal entries (1e-320) warn in the LU of det
        det = float(np.linalg.det(rotation))
    if off > RIGID_TOLERANCE or det < 0.0:
        raise ValueError(f"its 3x3 part is not a rotation (R'R differs from identity by {off:.3g}, det "
                         f"{det:.3g}): expected orthonormal axes with det +1")
    return matrix


RigidTransform = Annotated[Matrix4, AfterValidator(_rigid)]


class RigSource(_Strict):
    """A rig preset, or a stereo calibration file on a mast of the given height, or both: the
    preset's mast and HRC with the calibrated navigation pair."""

    preset: str | None = None
    calibration: str | None = Field(None, description="OpenCV YAML, Kalibr camchain, MATLAB stereoParameters .mat "
                                    "or left camera_info")
    calibration_right: str | None = Field(None, description="right camera_info (with a camera_info left)")
    calibration_image_size: tuple[int, int] | None = Field(
        None, description="width, height px: for a MATLAB calibration that does not record it")
    mast_height_m: float = Field(1.5, gt=0.0, le=20.0)
    body_T_left: RigidTransform | None = Field(
        None, description="4x4: the navigation pair's left camera in the body frame, for a body-fixed pair "
        "(default: on the mast at pan 0 and traverse_tilt_rad)")
    rectification: Matrix3 | None = Field(
        None, description="3x3: a rectified calibration's left camera axes in the camera as mounted (the "
        "transpose of stereoRectify's R1), when the images were rectified before the calibration was written")


class MapSource(_Strict):
    """An orbital map of the traverse's ground: GeoTIFFs (paths relative to the folder) and the
    accuracy its producer states for its georeference."""

    name: str = Field(min_length=1)
    dtm: str = Field(description="DTM GeoTIFF: heights above the body's reference surface, a projected CRS")
    orthoimage: str | None = Field(None, description="orthoimage GeoTIFF, one grey band, the DTM's CRS")
    offset_sigma_m: float = Field(3.0, gt=0.0, le=10000.0, description="1-sigma horizontal georeference error, "
                                  "per axis")
    vertical_sigma_m: float = Field(1.0, gt=0.0, le=10000.0, description="1-sigma offset of its heights")
    rotation_sigma_deg: float = Field(0.02, gt=0.0, le=10.0, description="1-sigma rotation about the origin")


class Manifest(_Strict):
    name: str
    seed: int = Field(0, description="seeds the tie-point selection at sites")
    origin: OriginConfig
    rig: RigSource
    image_noise_px: float = Field(gt=0.0, le=50.0)
    traverse_tilt_rad: float = Field(ge=-1.5708, le=1.5708, description="mast tilt of the navigation stereo pair "
                                     "(pan 0)")
    gps_lever_arm_m: tuple[LeverArm, LeverArm, LeverArm] = (0.0, 0.0, 0.0)
    start_world_T_body: RigidTransform = Field(description="4x4, surveyed start pose in local ENU")
    start_sigmas: tuple[Sigma, Sigma, Sigma, Sigma, Sigma, Sigma] = Field(
        description="rotation rad x3, position m x3 (1 sigma)")
    wheel_slip_mean: float = Field(0.0, ge=-0.5, le=1.0, description="expected odometry slip shared along the "
                                   "traverse")
    wheel_slip_sigma: float = Field(0.05, gt=0.0, le=1.0, description="its uncertainty (1 sigma)")
    estimator: EstimatorConfig = EstimatorConfig()
    maps: list[MapSource] = Field(default_factory=list, description="orbital maps (the orbital kind)")


@dataclass(frozen=True)
class PanoramaImage:
    """One image frame of a site panorama (a WAC stereo pair) or an HRC frame, at mast angles."""

    stop: int
    site: int
    camera: str  # "wac" (left and right) or "hrc" (left only)
    pan_rad: float
    tilt_rad: float
    left: Path
    right: Path | None = None


