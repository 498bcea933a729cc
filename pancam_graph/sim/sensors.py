"""Measurement-level sensor models: what each instrument reports, with noise and outliers."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..config import CameraConfig, DeadReckoningConfig, GpsConfig
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera, Rig
from ..records import DeadReckoning, GpsFix, HrcFrame, StereoObservations

if TYPE_CHECKING:
    from .errors import TrueRig


class LandmarkField:
    """Landmarks with a KD-tree for range queries."""

    def __init__(self, points: np.ndarray):
        self.points = points
        self.tree = cKDTree(points)

    def near(self, centre: np.ndarray, radius_m: float) -> np.ndarray:
        return np.asarray(self.tree.query_ball_point(centre, radius_m), dtype=np.int64)


def _visible_in_camera(
    field: LandmarkField, world_T_cam: np.ndarray, camera: Camera, range_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Indices and camera-frame coordinates of landmarks in range and in front of the camera."""
    ids = field.near(world_T_cam[:3, 3], range_m[1])
    if len(ids) == 0:
        return ids, np.zeros((0, 3))
    rot, t = world_T_cam[:3, :3], world_T_cam[:3, 3]
    p_cam = (field.points[ids] - t) @ rot
    keep = p_cam[:, 2] > max(range_m[0], 0.1)
    return ids[keep], p_cam[keep]


def observe_stereo(
    field: LandmarkField,
    world_T_body: np.ndarray,
    body_T_left: gtsam.Pose3,
    rig: Rig,
    range_m: tuple[float, float],
    cam_cfg: CameraConfig,
    rng: np.random.Generator,
    true_rig: TrueRig | None = None,
    true_body_T_left: gtsam.Pose3 | None = None,
    tracking: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> StereoObservations:
    """Rectified stereo measurements (u_left, u_right, v) of landmarks seen by both cameras at
    `body_T_left`. Where the calibration is off (`true_rig`) or the camera really points
    elsewhere (`true_body_T_left`), the pixels are the true pair's at the true pose, but the
    landmarks seen are the nominal ones: the noise drawn after them is the ideal simulation's,
    draw for draw, so an error's effect is not mixed with another noise draw. `tracking`
    (sim.errors.TrackingErrors) gives the track ids and pixel errors in place of the landmark
    ids and the white noise, which is still drawn, so that every later draw is the same.

    Outliers are false matches: the track id is kept, the pixels are random in the image.
    """
    world_T_left = world_T_body @ body_T_left.matrix()
    ids, p_cam = _visible_in_camera(field, world_T_left, rig.wac, range_m)
    cam = rig.wac
    uv = cam.project(p_cam, distort=False)
    u_right = uv[:, 0] - cam.fx * rig.baseline_m / p_cam[:, 2]
    inside = cam.in_image(uv) & (u_right >= 0.0)
    ids, uv, u_right = ids[inside], uv[inside], u_right[inside]
    if true_rig is not None or true_body_T_left is not None:
        world_T_true = world_T_body @ (true_body_T_left or body_T_left).matrix()
        p_true = (field.points[ids] - world_T_true[:3, 3]) @ world_T_true[:3, :3]
        if true_rig is None:
            uv = cam.project(p_true, distort=False)
            u_right = uv[:, 0] - cam.fx * rig.baseline_m / p_true[:, 2]
        else:
            uv, u_right = true_rig.observe(p_true)
    uvv = np.column_stack([uv[:, 0], u_right, uv[:, 1]])
    white = rng.normal(0.0, cam_cfg.image_noise_px, uvv.shape)
    if tracking is None:
        uvv += white
    else:
        ids, errors = tracking(ids)
        uvv += errors
    bad = rng.random(len(ids)) < cam_cfg.outlier_fraction
    n_bad = int(bad.sum())
    if n_bad:
        u_l = rng.uniform(0, cam.width - 1, n_bad)
        uvv[bad] = np.column_stack(
            [u_l, u_l - rng.uniform(0.5, 60.0, n_bad), rng.uniform(0, cam.height - 1, n_bad)]
        )
    return StereoObservations(ids, uvv)


def observe_hrc(
    field: LandmarkField,
    world_T_body: np.ndarray,
    pan_rad: float,
    tilt_rad: float,
    rig: Rig,
    range_m: tuple[float, float],
    cam_cfg: CameraConfig,
    rng: np.random.Generator,
    true_angles: tuple[float, float] | None = None,
) -> HrcFrame:
    """HRC measurements of the frame taken at (pan_rad, tilt_rad); with `true_angles`, the
    pixels are the true pointing's, of the landmarks the nominal one sees (as observe_stereo)."""
    world_T_hrc = world_T_body @ rig.body_T_hrc(pan_rad, tilt_rad).matrix()
    ids, p_cam = _visible_in_camera(field, world_T_hrc, rig.hrc, range_m)
    uv = rig.hrc.project(p_cam, distort=False)
    inside = rig.hrc.in_image(uv)
    ids, uv = ids[inside], uv[inside]
    if true_angles is not None:
        world_T_true = world_T_body @ rig.body_T_hrc(*true_angles).matrix()
        uv = rig.hrc.project((field.points[ids] - world_T_true[:3, 3]) @ world_T_true[:3, :3], distort=False)
    uv = uv + rng.normal(0.0, cam_cfg.image_noise_px, (len(ids), 2))
    bad = rng.random(len(ids)) < cam_cfg.outlier_fraction
    uv[bad] = rng.uniform(0, rig.hrc.width - 1, (int(bad.sum()), 2))
    return HrcFrame(pan_rad, tilt_rad, ids, uv)


def gps_fix(
    world_T_body: np.ndarray,
    time_s: float,
    cfg: GpsConfig,
    frame: LocalFrame,
    rng: np.random.Generator,
) -> GpsFix:
    """A WGS84 fix of the antenna with Gaussian noise and, sometimes, a multipath jump."""
    antenna = world_T_body[:3, :3] @ np.asarray(cfg.lever_arm_m) + world_T_body[:3, 3]
    noise = rng.normal(0.0, [cfg.sigma_horizontal_m, cfg.sigma_horizontal_m, cfg.sigma_vertical_m])
    if rng.random() < cfg.multipath_fraction:
        angle = rng.uniform(0, 2 * np.pi)
        noise[:2] += rng.uniform(*cfg.multipath_offset_m) * np.array([np.cos(angle), np.sin(angle)])
    lat, lon, h = frame.to_geodetic(antenna + noise)[0]
    return GpsFix(time_s, float(lat), float(lon), float(h), cfg.sigma_horizontal_m, cfg.sigma_vertical_m)


def dead_reckoning(
    world_T_prev: np.ndarray, world_T_curr: np.ndarray, dt_s: float, cfg: DeadReckoningConfig,
    traverse_slip: float, rng: np.random.Generator,
) -> DeadReckoning:
    """Wheel odometry (distance scaled by the traverse's slip plus step noise) and IMU (heading
    increment with noise and gyro drift, absolute roll/pitch from gravity) between two stops, with
    the covariance of this step's own noise; the shared slip is the traverse's SlipPrior."""
    true = gtsam.Pose3(world_T_prev).between(gtsam.Pose3(world_T_curr))
    distance = float(np.linalg.norm(true.translation()))
    slip = rng.normal(traverse_slip, cfg.wheel_slip_sigma)
    heading_sigma = np.hypot(np.deg2rad(cfg.heading_noise_deg), np.deg2rad(cfg.gyro_drift_deg_per_h) * dt_s / 3600)
    tilt_sigma = np.deg2rad(cfg.tilt_noise_deg) * np.sqrt(2.0)
    d_yaw = rng.normal(0.0, heading_sigma)
    d_tilt = rng.normal(0.0, tilt_sigma, 2)
    ypr = true.rotation().ypr()
    rot = gtsam.Rot3.Ypr(ypr[0] + d_yaw, ypr[1] + d_tilt[0], ypr[2] + d_tilt[1])
    direction = true.translation() / distance if distance > 1e-9 else np.array([1.0, 0.0, 0.0])
    # The drive direction is known to the odometry only as well as the heading.
    direction = gtsam.Rot3.Rz(0.5 * d_yaw).rotate(direction)
    measured = gtsam.Pose3(rot, direction * distance * (1.0 + slip))

    along = cfg.wheel_slip_sigma * distance + 0.005
    cross = heading_sigma * distance + 0.01 * distance + 0.005
    vertical = 0.02 * distance + 0.005
    # Translation sigmas are along/cross/vertical in the previous body frame; GTSAM wants them
    # in the current one, so rotate the block.
    prev_R_curr = rot.matrix()
    heading = np.arctan2(direction[1], direction[0])
    along_R = gtsam.Rot3.Rz(heading).matrix()
    cov_t_prev = along_R @ np.diag([along, cross, vertical]) ** 2 @ along_R.T
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.diag([tilt_sigma, tilt_sigma, heading_sigma]) ** 2
    block = prev_R_curr.T @ cov_t_prev @ prev_R_curr
    cov[3:, 3:] = 0.5 * (block + block.T)  # exactly symmetric, as a covariance file stores it
    return DeadReckoning(measured.matrix(), cov)
