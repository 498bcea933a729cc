"""Factor builders: one function per measurement type, taking records, returning GTSAM factors."""

from __future__ import annotations

import gtsam
import numpy as np

from ..errors import GraphError
from . import noise
from .keys import L, X


def start_prior(world_T_body: np.ndarray, sigmas: np.ndarray) -> gtsam.PriorFactorPose3:
    """Fixes the gauge: the surveyed start pose."""
    return gtsam.PriorFactorPose3(X(0), gtsam.Pose3(world_T_body), noise.pose_sigmas(sigmas[:3], sigmas[3:]))


def motion(i: int, j: int, prev_T_curr: gtsam.Pose3, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """Relative body motion between stops i and j (VO or dead reckoning)."""
    return gtsam.BetweenFactorPose3(X(i), X(j), prev_T_curr, noise.pose_covariance(covariance))


def landmark_anchor(stop: int, track: int, p_body: np.ndarray, sigma_m: float = 3.0) -> gtsam.BearingRangeFactor3D:
    """Weak bearing and range of landmark L(track) from the site X(stop) that first triangulated
    it, `p_body` in that site's body frame (see noise.landmark_anchor). Relative to the site, so
    it carries no information about where the site is."""
    p_body = np.asarray(p_body, dtype=float)
    rng_m = float(np.linalg.norm(p_body))
    if not np.all(np.isfinite(p_body)) or rng_m <= 0.0:
        raise GraphError(f"landmark anchor of track {track} at stop {stop}: no usable triangulation")
    return gtsam.BearingRangeFactor3D(X(stop), L(track), gtsam.Unit3(p_body), rng_m,
                                      noise.landmark_anchor(rng_m, sigma_m))


def stereo(
    stop: int, track: int, uvv: np.ndarray, calibration: gtsam.Cal3_S2Stereo, body_T_left: gtsam.Pose3,
    model: gtsam.noiseModel.Base,
) -> gtsam.GenericStereoFactor3D:
    """A rectified stereo measurement (u_left, u_right, v) of landmark L(track) from stop X(stop);
    the camera pose is body pose * (mast pan/tilt and extrinsics)."""
    if not np.all(np.isfinite(uvv)):
        raise GraphError(f"non-finite stereo measurement of track {track} at stop {stop}")
    return gtsam.GenericStereoFactor3D(
        gtsam.StereoPoint2(*map(float, uvv)), model, X(stop), L(track), calibration, body_T_left
    )


def projection(
    stop: int, track: int, uv: np.ndarray, calibration: gtsam.Cal3_S2, body_T_cam: gtsam.Pose3,
    model: gtsam.noiseModel.Base,
) -> gtsam.GenericProjectionFactorCal3_S2:
    """A monocular (HRC) measurement (u, v) of landmark L(track) from stop X(stop)."""
    if not np.all(np.isfinite(uv)):
        raise GraphError(f"non-finite HRC measurement of track {track} at stop {stop}")
    return gtsam.GenericProjectionFactorCal3_S2(
        np.asarray(uv, dtype=float), model, X(stop), L(track), calibration, body_T_cam
    )


def gps(stop: int, antenna_enu: np.ndarray, lever_arm_m: np.ndarray, model: gtsam.noiseModel.Base):
    """An ENU antenna position (never latitude/longitude) with the body-frame lever arm, at stop X(stop)."""
    return gps_at(X(stop), antenna_enu, lever_arm_m, model)


def gps_at(pose_key: int, antenna_enu: np.ndarray, lever_arm_m: np.ndarray, model: gtsam.noiseModel.Base):
    """An ENU antenna position with the body-frame lever arm, on any pose variable."""
    antenna_enu = np.asarray(antenna_enu, dtype=float)
    if not np.all(np.isfinite(antenna_enu)):
        raise GraphError(f"non-finite GPS position for {gtsam.Symbol(pose_key).string()}")
    return gtsam.GPSFactorArm(pose_key, antenna_enu, np.asarray(lever_arm_m, dtype=float), model)


def between_error(measured: gtsam.Pose3, world_T_a: gtsam.Pose3,
                  world_T_b: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """GTSAM's BetweenFactor error, Logmap(measured^-1 a_T_b) ([rotation, translation]), with its
    Jacobians in the measurement's, world_T_a's and world_T_b's tangent spaces: for Python
    factors whose measurement depends on variables of their own (wheel slip, calibration)."""
    h_a, h_b = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    a_T_b = world_T_a.between(world_T_b, h_a, h_b)
    h_measured, h_relative = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    delta = measured.between(a_T_b, h_measured, h_relative)
    h_log = np.zeros((6, 6), order="F")
    error = gtsam.Pose3.Logmap(delta, h_log)
    return error, h_log @ h_measured, h_log @ h_relative @ h_a, h_log @ h_relative @ h_b


def between(key_a: int, key_b: int, a_T_b: gtsam.Pose3, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
    """Relative body motion between any two pose variables."""
    return gtsam.BetweenFactorPose3(key_a, key_b, a_T_b, noise.pose_covariance(covariance))
