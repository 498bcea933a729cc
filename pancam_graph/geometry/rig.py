"""Camera and rig models: intrinsics, stereo pairs, HRC and pan/tilt mast kinematics.

Frames (docs/design.md section 3): rover body x forward, y left, z up with the origin on
the ground under the mast; the mast head frame has the same axes after pan (about z)
and tilt (about the panned y axis, positive looks up); camera frames are OpenCV
(x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

# Rotation taking camera-frame vectors (x right, y down, z forward) into the
# head frame (x forward, y left, z up).
HEAD_R_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

# A camera fixed at the body origin looking forward (a car's or a rover's navigation pair when
# the body frame is put at the left camera): body_T_camera.
BODY_T_FORWARD_CAMERA = np.eye(4)
BODY_T_FORWARD_CAMERA[:3, :3] = HEAD_R_CAM


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with OpenCV's distortion: radial (k1, k2, k3), tangential (p1, p2) and thin
    prism (s1..s4), OpenCV's order and formulas. The thin prism and k3 carry what a CAHVOR
    model's tilted optical axis leaves (geometry/cahvor.to_photogrammetric)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def _thin_prism(self) -> bool:
        return any((self.s1, self.s2, self.s3, self.s4))

    def distortion(self) -> np.ndarray:
        """OpenCV's distortion vector, as short as its terms allow (4, 5 or 12 numbers)."""
        if self._thin_prism:
            return np.array([self.k1, self.k2, self.p1, self.p2, self.k3, 0.0, 0.0, 0.0,
                             self.s1, self.s2, self.s3, self.s4])
        if self.k3:
            return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def project(self, p_cam: np.ndarray, distort: bool = True) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3); points must have z > 0."""
        p = np.atleast_2d(np.asarray(p_cam, dtype=float))
        x = p[:, 0] / p[:, 2]
        y = p[:, 1] / p[:, 2]
        if distort:
            r2 = x * x + y * y
            radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
            if self.k3:
                radial = radial + self.k3 * r2 * r2 * r2
            xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
            yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
            if self._thin_prism:
                xd = xd + self.s1 * r2 + self.s2 * r2 * r2
                yd = yd + self.s3 * r2 + self.s4 * r2 * r2
            x, y = xd, yd
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        uv = np.atleast_2d(uv)
        return (
            (uv[:, 0] >= margin_px)
            & (uv[:, 0] <= self.width - 1 - margin_px)
            & (uv[:, 1] >= margin_px)
            & (uv[:, 1] <= self.height - 1 - margin_px)
        )

    def gtsam_calibration(self) -> gtsam.Cal3_S2:
        """Calibration of the rectified (undistorted) image."""
        return gtsam.Cal3_S2(self.fx, self.fy, 0.0, self.cx, self.cy)


def camera_from_angular_resolution(ifov_urad: float, size_px: int = 1024) -> Camera:
    f = 1.0 / (ifov_urad * 1e-6)
    c = (size_px - 1) / 2.0
    return Camera(fx=f, fy=f, cx=c, cy=c, width=size_px, height=size_px)


def camera_from_optics(focal_mm: float, pixel_um: float, size_px: int = 1024) -> Camera:
    f = focal_mm * 1e3 / pixel_um
    c = (size_px - 1) / 2.0
    return Camera(fx=f, fy=f, cx=c, cy=c, width=size_px, height=size_px)


@dataclass(frozen=True)
class Rig:
    """A stereo camera pair (rectified, left camera is the reference) and an optional HRC
    on a pan/tilt mast.

    `hrc_offset_m` is the HRC's position along the head's -y axis (to the right) from the
    left WAC; both WACs and the HRC look along the head's x axis.
    """

    name: str
    wac: Camera
    baseline_m: float
    mast_height_m: float
    hrc: Camera | None = None
    hrc_offset_m: float = 0.0
    head_forward_offset_m: float = 0.0  # optical centres ahead of the tilt axis
    # A calibrated pair: the rectified left camera's axes in the raw left camera's frame, row by
    # row (rectification turns the camera a little); None: the pair is rectified as mounted.
    raw_R_rectified: tuple[float, ...] | None = None

    def head_T_left(self) -> gtsam.Pose3:
        """The (rectified) left camera in the head frame."""
        t = np.array([self.head_forward_offset_m, self.baseline_m / 2.0, 0.0])
        return gtsam.Pose3(gtsam.Rot3(HEAD_R_CAM @ self.rectification()), t)

    def rectification(self) -> np.ndarray:
        """raw_R_rectified as a 3x3 matrix (identity when the pair is rectified as mounted)."""
        return np.eye(3) if self.raw_R_rectified is None else np.array(self.raw_R_rectified).reshape(3, 3)

    def head_T_hrc(self) -> gtsam.Pose3:
        if self.hrc is None:
            raise ValueError(f"rig {self.name!r} has no HRC")
        t = np.array([self.head_forward_offset_m, self.baseline_m / 2.0 - self.hrc_offset_m, 0.0])
        return gtsam.Pose3(gtsam.Rot3(HEAD_R_CAM), t)

    def body_T_head(self, pan_rad: float, tilt_rad: float) -> gtsam.Pose3:
        """Mast kinematics: body -> pan (about z, positive left) -> tilt (positive up)."""
        body_T_pan = gtsam.Pose3(gtsam.Rot3.Rz(pan_rad), np.array([0.0, 0.0, self.mast_height_m]))
        pan_T_head = gtsam.Pose3(gtsam.Rot3.Ry(-tilt_rad), np.zeros(3))
        return body_T_pan.compose(pan_T_head)

    def body_T_left(self, pan_rad: float, tilt_rad: float) -> gtsam.Pose3:
        return self.body_T_head(pan_rad, tilt_rad).compose(self.head_T_left())

    def body_T_hrc(self, pan_rad: float, tilt_rad: float) -> gtsam.Pose3:
        return self.body_T_head(pan_rad, tilt_rad).compose(self.head_T_hrc())

    def stereo_calibration(self) -> gtsam.Cal3_S2Stereo:
        c = self.wac
        return gtsam.Cal3_S2Stereo(c.fx, c.fy, 0.0, c.cx, c.cy, self.baseline_m)


def _exomars() -> Rig:
    # docs/design.md section 2: WAC 580 urad/px (f = 1724 px), HRC 82 urad/px (f = 12195 px),
    # HRC 0.154 m right of the rig centre -> 0.404 m from the left WAC.
    return Rig(
        name="exomars",
        wac=camera_from_angular_resolution(580.0),
        baseline_m=0.50,
        mast_height_m=1.5,
        hrc=camera_from_angular_resolution(82.0),
        hrc_offset_m=0.404,
    )


def _mer_navcam() -> Rig:
    return Rig("mer_navcam", camera_from_angular_resolution(820.0), baseline_m=0.20, mast_height_m=1.54)


def _mer_pancam() -> Rig:
    return Rig("mer_pancam", camera_from_angular_resolution(280.0), baseline_m=0.30, mast_height_m=1.54)


def _prototype() -> Rig:
    # 21 mm lens, 12 um pixels; HRC 50 mm lens, 2.2 um pixels binned 2x2 (4.4 um), ~5 deg FOV.
    return Rig(
        name="prototype",
        wac=camera_from_optics(21.0, 12.0),
        baseline_m=0.50,
        mast_height_m=1.5,
        hrc=camera_from_optics(50.0, 4.4, size_px=992),
        hrc_offset_m=0.404,
    )


def _katwijk_pancam() -> Rig:
    # The ExoMars PanCam emulator's WAC pair as calibrated for ESA's Katwijk beach data set
    # (shared/data/real/katwijk_pancam_calib/PanCam_calibstruct.mat), rectified by OpenCV's
    # stereoRectify; tests/formats/test_calibration.py checks these numbers against that file. The file
    # records no image size: 1280 x 960 is inferred (the principal points lie within 20 px of its
    # centre; the calibration points reach 1196 x 921). On the ExoMars mast height; no HRC.
    wac = Camera(fx=1446.2898299710705, fy=1446.2898299710705, cx=641.9771499633789, cy=472.0479431152344,
                 width=1280, height=960)
    raw_R_rectified = (0.9999457491091042, 0.0019256124045044505, -0.010236740472432974,
                       -0.0019756160235994713, 0.9999861565182645, -0.004876854842638292,
                       0.01022720782812327, 0.004896814137425077, 0.9999357106491116)
    return Rig("katwijk_pancam", wac, baseline_m=0.5024427796641896, mast_height_m=1.5,
               raw_R_rectified=raw_R_rectified)


RIG_PRESETS = {
    "exomars": _exomars,
    "katwijk_pancam": _katwijk_pancam,
    "mer_navcam": _mer_navcam,
    "mer_pancam": _mer_pancam,
    "prototype": _prototype,
}


def rig_preset(name: str) -> Rig:
    try:
        return RIG_PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown rig preset {name!r}; choose one of {sorted(RIG_PRESETS)}") from None


def triangulate_rectified(u_left, u_right, v, camera: Camera, baseline_m: float) -> np.ndarray:
    """Seed eq. (2.28): points (N, 3) in the left camera frame from a rectified stereo pair.

    X = B (x - u0) / d, Y = B (y - v0) / d, Z = B f / d with disparity d = x - x'.
    Rows with non-positive disparity come back as NaN.
    """
    u_left = np.asarray(u_left, dtype=float)
    d = u_left - np.asarray(u_right, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(d > 0, baseline_m / d, np.nan)
    x = scale * (u_left - camera.cx)
    y = scale * (np.asarray(v, dtype=float) - camera.cy) * camera.fx / camera.fy
    z = scale * camera.fx
    return np.column_stack([x, y, z])


def project_rectified(points: np.ndarray, camera: Camera, baseline_m: float) -> np.ndarray:
    """(u_left, u_right, v) (N, 3) of points (N, 3) in the left camera frame through the rectified
    pair (triangulate_rectified's inverse; GTSAM's StereoCamera.project2); NaN behind the camera."""
    points = np.asarray(points, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_depth = np.where(points[:, 2] > 0, 1.0 / points[:, 2], np.nan)
    u_left = camera.fx * points[:, 0] * inverse_depth + camera.cx
    return np.column_stack([u_left, u_left - camera.fx * baseline_m * inverse_depth,
                            camera.fy * points[:, 1] * inverse_depth + camera.cy])


def triangulation_jacobian(points: np.ndarray, baseline_m: float, fx: float, fy: float | None = None) -> np.ndarray:
    """d(X, Y, Z) / d(u_left, u_right, v) of eq. (2.28) at left-camera points (N, 3): the dissertation's
    (3.2) with the elevation row kept. With disparity d = B fx / Z:
    [[(B - X) / d, X / d, 0], [-Y / d, Y / d, B fx / (d fy)], [-Z / d, Z / d, 0]]."""
    x, y, z = np.atleast_2d(np.asarray(points, dtype=float)).T
    d = baseline_m * fx / z
    jac = np.zeros((len(x), 3, 3))  # rows X, Y, Z; columns u_left, u_right, v
    jac[:, 0, 0], jac[:, 0, 1] = (baseline_m - x) / d, x / d
    jac[:, 1, 0], jac[:, 1, 1], jac[:, 1, 2] = -y / d, y / d, baseline_m / d * fx / (fy or fx)
    jac[:, 2, 0], jac[:, 2, 1] = -z / d, z / d
    return jac


def triangulation_covariance(points: np.ndarray, camera: Camera, baseline_m: float, sigma_px: float) -> np.ndarray:
    """Covariances (N, 3, 3) of `triangulate_rectified`'s left-camera points (N, 3) for independent
    pixel noise `sigma_px` on (u_left, u_right, v): J J^T sigma^2."""
    jac = triangulation_jacobian(points, baseline_m, camera.fx, camera.fy)
    return sigma_px**2 * jac @ np.transpose(jac, (0, 2, 1))
