"""The stereo pair's calibration error as one unknown shared by every stereo view at the sites.

A stereo pair is calibrated once, on the ground; what is left of its error is the same in every
frame of the traverse. Both focal lengths off by a ratio s, the right camera's off by a further
ratio e, and the right camera turned by a small rotation w (rad, in the left camera's axes)
move the pixels, to first order, by

    du_left = s (u_left - cx),   dv = s (v - cy),
    du_right = s (u_right - cx) + f (w_x x y - w_y (1 + x^2) + w_z y + e x),
    x, y = (u_right - cx, v - cy) / f

(sim/errors.py's TrueRig is that error). About the vertical (w_y) it is a disparity bias of
f w_y (0.3 px for 0.01 deg on the WAC) that scales every range by (1 + Z w_y / B): a site's
landmarks come out nearer or farther by a fraction growing with their range, the same at every
site. Treated as independent pixel noise it cannot average out, and the sites' estimate is
over-confident (docs/simulation_errors.md). Here (w_x, w_y, w_z, e, s) are one 5-vector C(0)
shared by the whole traverse, with the calibration's own stated sigmas as its prior, and every
site stereo view becomes a factor on its pose, its landmark and C(0): ties seen from sites at
different ranges and in different parts of the frames observe it. (The baseline's own error is
a scale of every range, which nothing but an absolute reference observes.)

The VO's steps are solved in the front-end before the graph sees them: their share of the error
is a scale of every step, which the vo_scale kind carries.
"""

from __future__ import annotations

import gtsam
import numpy as np
from pydantic import Field

from ..errors import GraphError
from ..graph import keys, noise
from .base import Kind, Section


def pixel_coefficients(uvv: np.ndarray, focal_px: float, cx: float, cy: float) -> np.ndarray:
    """d (u_left, u_right, v) / d (w_x, w_y, w_z, e, s) at a measured (u_left, u_right, v): 3 x 5."""
    x, y = (uvv[1] - cx) / focal_px, (uvv[2] - cy) / focal_px
    return np.array([[0.0, 0.0, 0.0, 0.0, uvv[0] - cx],
                     [focal_px * x * y, -focal_px * (1.0 + x * x), focal_px * y, focal_px * x, uvv[1] - cx],
                     [0.0, 0.0, 0.0, 0.0, uvv[2] - cy]])


RIGHT_CAMERA = keys.C(0)
NAMES = ("right_rotation_x_rad", "right_rotation_y_rad", "right_rotation_z_rad", "right_focal_ratio", "focal_scale")


def calibrated_stereo_error(measured: np.ndarray, coefficients: np.ndarray, calibration: gtsam.Cal3_S2Stereo,
                            body_T_left: gtsam.Pose3, world_T_body: gtsam.Pose3, point: np.ndarray,
                            calibration_error: np.ndarray, jacobians: list | None = None) -> np.ndarray:
    """GTSAM's stereo residual (predicted - measured, u_left, u_right, v) with the prediction
    moved by the calibration error; a point behind the camera gives GTSAM's own
    answer (2 f, zero Jacobians)."""
    h_pose = np.zeros((6, 6), order="F")
    world_T_left = world_T_body.compose(body_T_left, h_pose, None)
    h_camera, h_point = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
    try:
        predicted = gtsam.StereoCamera(world_T_left, calibration).project2(point, h_camera, h_point)
    except RuntimeError:  # StereoCheiralityException
        if jacobians is not None:
            jacobians[0], jacobians[1], jacobians[2] = np.zeros((3, 6)), np.zeros((3, 3)), np.zeros((3, len(NAMES)))
        return np.full(3, 2.0 * calibration.fx())
    error = np.array([predicted.uL(), predicted.uR(), predicted.v()]) + coefficients @ calibration_error - measured
    if jacobians is not None:
        jacobians[0] = h_camera @ h_pose
        jacobians[1] = h_point
        jacobians[2] = coefficients
    return error


def calibrated_stereo_factor(stop_key: int, landmark_key: int, uvv: np.ndarray, camera: tuple[float, ...],
                             body_T_left: np.ndarray, model: tuple[str, float, float | None]) -> gtsam.CustomFactor:
    """A site's stereo view (u_left, u_right, v) of a landmark, with the calibration error in it.
    Plain arguments only (`camera` = (fx, fy, cx, cy, baseline), the mount as a 4x4 matrix,
    `model` = (kernel, sigma_px, k)): a checkpoint pickles them to make the factor again."""
    if not np.all(np.isfinite(uvv)):
        raise GraphError(f"non-finite stereo measurement of {gtsam.Symbol(landmark_key).string()}")
    fx, fy, cx, cy, baseline = camera
    calibration = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, baseline)
    mount = gtsam.Pose3(body_T_left)
    measured = np.asarray(uvv, dtype=float)
    coefficients = pixel_coefficients(measured, fx, cx, cy)

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        pose_key, point_key, calibration_key = factor.keys()
        return calibrated_stereo_error(measured, coefficients, calibration, mount, values.atPose3(pose_key),
                                       values.atPoint3(point_key), values.atVector(calibration_key), jacobians)

    kernel, sigma_px, k = model
    return gtsam.CustomFactor(noise.robust(kernel, noise.stereo_pixels(sigma_px), k),
                              [stop_key, landmark_key, RIGHT_CAMERA], error)


class StereoCalibrationSettings(Section):
    """[estimator.stereo_calibration]"""

    rotation_sigma_deg: float = Field(0.01, gt=0.0, le=5.0, description="1-sigma of the right camera's rotation "
                                      "left by its calibration, per axis (the project's calibration of the "
                                      "rendered control field: 0.005-0.017 deg)")
    focal_ratio_sigma: float = Field(5e-5, gt=0.0, le=0.05, description="1-sigma of the two cameras' focal ratio "
                                     "left by the calibration (the same calibration: 0.002-0.007 %)")
    focal_scale_sigma: float = Field(3e-4, gt=0.0, le=0.05, description="1-sigma of both focal lengths' common "
                                     "error left by the calibration (the same calibration: fx to 0.54 px of 1,724)")


class StereoCalibration(Kind):
    name = "stereo_calibration"
    order = 10
    Settings = StereoCalibrationSettings
    needs = {"sites": "it calibrates the sites' stereo views"}
    builds_site_stereo = True

    def __init__(self, localizer):
        super().__init__(localizer)
        settings: StereoCalibrationSettings = localizer.estimator.stereo_calibration
        rotation = np.deg2rad(settings.rotation_sigma_deg)
        prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([rotation, rotation, rotation, settings.focal_ratio_sigma,
                                                           settings.focal_scale_sigma]))
        localizer.smoother.add(gtsam.PriorFactorVector(RIGHT_CAMERA, np.zeros(len(NAMES)), prior))
        localizer.smoother.insert(RIGHT_CAMERA, np.zeros(len(NAMES)), shared=True)

    def site_stereo_factor(self):
        return calibrated_stereo_factor

    def true_values(self, truth, values: gtsam.Values) -> bool:
        # zero where the truth has none (real data, or a simulation with a trusted pair)
        known = truth.kinds.get(self.name, {})
        values.insert(RIGHT_CAMERA, np.array([float(known.get(name, 0.0)) for name in NAMES]))
        return True

    def against_truth(self, truth) -> dict[str, float]:
        known = truth.kinds.get(self.name)
        if not known:
            return {}
        estimate = self.loc.smoother.vector(RIGHT_CAMERA)
        return {f"{name}_error": float(estimate[i] - known[name]) for i, name in enumerate(NAMES)}

    def counters(self) -> dict:
        estimate = self.loc.smoother.vector(RIGHT_CAMERA)
        sigmas = np.sqrt(np.diag(self.loc.smoother.marginal_covariance(RIGHT_CAMERA)))
        counts = {}
        for i, name in enumerate(NAMES):
            counts[name], counts[f"{name}_sigma"] = float(estimate[i]), float(sigmas[i])
        return counts
