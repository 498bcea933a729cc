"""A calibrated stereo pair as OpenCV models it (intrinsics, distortion, R and T), and the
rectified pair the back-end works in (OpenCV's stereoRectify when the pair is not rectified).
The files these come from are read in formats/calibration.py."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..errors import InputError
from .rig import Camera, Rig


@dataclass(frozen=True)
class RectifiedStereo:
    """A rectified stereo pair: the left camera's pinhole model and the baseline (m), and the
    rectified left camera's axes in the calibrated (raw) left camera's frame (rectification turns
    the camera a little; identity when the pair came rectified)."""

    camera: Camera
    baseline_m: float
    raw_R_rectified: np.ndarray = field(default_factory=lambda: np.eye(3), compare=False)

    def of(self, rig: Rig) -> Rig:
        """`rig` with this pair as its WACs: what images rectified by it are taken with."""
        return replace(rig, wac=self.camera, baseline_m=self.baseline_m,
                       raw_R_rectified=tuple(self.raw_R_rectified.ravel().tolist()))


@dataclass(frozen=True)
class RectificationMaps:
    """Pixel maps taking raw (distorted, unaligned) images to the rectified pair (cv2.remap)."""

    left: tuple[np.ndarray, np.ndarray]
    right: tuple[np.ndarray, np.ndarray]

    def __call__(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (cv2.remap(left, *self.left, cv2.INTER_LINEAR),
                cv2.remap(right, *self.right, cv2.INTER_LINEAR))


@dataclass(frozen=True)
class StereoCalibration:
    """Two calibrated cameras as OpenCV's stereoCalibrate gives them: intrinsics K, distortion D
    (OpenCV order), image size (width, height), and R, T taking left-camera points to the
    right camera (x_right = R x_left + T)."""

    source: str
    k_left: np.ndarray
    d_left: np.ndarray
    k_right: np.ndarray
    d_right: np.ndarray
    size: tuple[int, int]
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.translation))

    def left_T_right(self) -> np.ndarray:
        """The right camera's pose in the left camera's frame (4x4): the inverse of (R, T)."""
        right_T_left = np.eye(4)
        right_T_left[:3, :3], right_T_left[:3, 3] = self.rotation, self.translation
        return np.linalg.inv(right_T_left)

    def cameras(self) -> tuple[Camera, Camera]:
        """The left and right cameras as calibrated (their first four distortion coefficients)."""
        w, h = self.size

        def camera(k: np.ndarray, d: np.ndarray) -> Camera:
            k1, k2, p1, p2 = (float(v) for v in np.pad(d, (0, 4))[:4])
            return Camera(fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), width=w,
                          height=h, k1=k1, k2=k2, p1=p1, p2=p2)

        return camera(self.k_left, self.d_left), camera(self.k_right, self.d_right)

    @property
    def is_rectified(self) -> bool:
        """Images already rectified: no distortion, identical cameras side by side."""
        t = self.translation / self.baseline_m
        return (not np.any(self.d_left) and not np.any(self.d_right) and np.allclose(self.k_left, self.k_right)
                and np.allclose(self.rotation, np.eye(3), atol=1e-9) and abs(abs(t[0]) - 1.0) < 1e-9)

    def stereo_rectify(self) -> tuple[np.ndarray, ...]:
        """OpenCV stereoRectify's R1, R2, P1, P2, Q, ROI1, ROI2 (zero disparity at infinity,
        only valid pixels: alpha 0)."""
        return cv2.stereoRectify(self.k_left, self.d_left, self.k_right, self.d_right, self.size, self.rotation,
                                 self.translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)

    def rectified(self) -> RectifiedStereo:
        """The pair after rectification (OpenCV stereoRectify, zero disparity at infinity, only
        valid pixels: alpha 0)."""
        r1, _, p1, p2, _, _, _ = self.stereo_rectify()
        w, h = self.size
        camera = Camera(fx=float(p1[0, 0]), fy=float(p1[1, 1]), cx=float(p1[0, 2]), cy=float(p1[1, 2]), width=w,
                        height=h)
        if not np.all(np.isfinite(p1)) or camera.fx <= 0 or camera.fy <= 0:
            raise InputError(f"{self.source}: the calibration gives no usable rectification (focal length "
                             f"{camera.fx:.4g} x {camera.fy:.4g} px after stereoRectify)")
        # stereoRectify's R1 takes raw left-camera vectors into the rectified frame
        return RectifiedStereo(camera, float(-p2[0, 3] / p2[0, 0]), np.asarray(r1, dtype=float).T)

    def rectification_maps(self) -> RectificationMaps:
        """The maps `rectified()`'s pair is made with (fixed-point, for a fast remap)."""
        r1, r2, p1, p2, _, _, _ = self.stereo_rectify()
        maps = [cv2.initUndistortRectifyMap(k, d, r, p, self.size, cv2.CV_16SC2)
                for k, d, r, p in ((self.k_left, self.d_left, r1, p1), (self.k_right, self.d_right, r2, p2))]
        return RectificationMaps(*maps)
