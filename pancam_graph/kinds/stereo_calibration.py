"""The stereo pair's calibration error as one unknown shared by every measurement through the pair.

A stereo pair is calibrated once, on the ground; what is left of its error is the same in every
frame of the traverse (its six terms and the pixels they move: geometry/calibration_error.py).
Treated as independent pixel noise it cannot average out, and the estimate is over-confident
(docs/simulation_errors.md). Here the six terms are one vector C(0) shared by the whole traverse,
with the calibration's own stated sigmas as its prior, and
- every site stereo view becomes a factor on its pose, its landmark and C(0): ties seen from
  sites at different ranges and in different parts of the frames observe it;
- every VO step becomes a factor on its two poses and C(0): the step as the two-stop adjustment
  would have measured it with the pair as C(0) says, to first order (Motion.calibration_sensitivity).
  A turn of the right camera about the vertical pitches every step alike (a range error growing
  with range tilts the ground ahead); shared by every step, it accumulates, and the sites see it.
The baseline's own error scales every range, the VO's and the sites' alike: nothing but an
absolute reference observes it, and its prior stays.
"""

from __future__ import annotations

import gtsam
import numpy as np
from pydantic import Field

from ..errors import GraphError
from ..geometry.calibration_error import NAMES, pixel_shift_derivative, pixel_shifts
from ..graph import factors, keys, noise
from .base import Kind, Section
from .motion import VisualOdometry

CALIBRATION = keys.C(0)


def calibrated_stereo_error(measured: np.ndarray, calibration: gtsam.Cal3_S2Stereo, body_T_left: gtsam.Pose3,
                            world_T_body: gtsam.Pose3, point: np.ndarray, calibration_error: np.ndarray,
                            jacobians: list | None = None) -> np.ndarray:
    """GTSAM's stereo residual (predicted - measured, u_left, u_right, v) with the prediction
    moved by the calibration error, the shift taken at the predicted pixel (pixel_shifts says why
    not at the measured one); a point behind the camera gives GTSAM's own answer (2 f, zero
    Jacobians)."""
    h_pose = np.zeros((6, 6), order="F")
    world_T_left = world_T_body.compose(body_T_left, h_pose, None)
    h_camera, h_point = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
    try:
        predicted = gtsam.StereoCamera(world_T_left, calibration).project2(point, h_camera, h_point)
    except RuntimeError:  # StereoCheiralityException
        if jacobians is not None:
            jacobians[0], jacobians[1], jacobians[2] = np.zeros((3, 6)), np.zeros((3, 3)), np.zeros((3, len(NAMES)))
        return np.full(3, 2.0 * calibration.fx())
    uvv = np.array([predicted.uL(), predicted.uR(), predicted.v()])
    fx, cx, cy = calibration.fx(), calibration.px(), calibration.py()
    coefficients = pixel_shifts(uvv, fx, cx, cy)
    error = uvv + coefficients @ calibration_error - measured
    if jacobians is not None:
        moved = np.eye(3) + pixel_shift_derivative(uvv, calibration_error, fx, cx, cy)
        jacobians[0] = moved @ h_camera @ h_pose
        jacobians[1] = moved @ h_point
        jacobians[2] = coefficients
    return error


def calibrated_stereo_factor(stop_key: int, landmark_key: int, uvv: np.ndarray, camera: tuple[float, ...],
                             body_T_left: np.ndarray,
                             model: tuple[str, float | None, float, float]) -> gtsam.CustomFactor:
    """A site's stereo view (u_left, u_right, v) of a landmark, with the calibration error in it.
    Plain arguments only (`camera` = (fx, fy, cx, cy, baseline), the mount as a 4x4 matrix,
    `model` = (kernel, k, sigma_px, tie_sigma_px): noise.robust and noise.stereo_tie's): a
    checkpoint pickles them to make the factor again."""
    if not np.all(np.isfinite(uvv)):
        raise GraphError(f"non-finite stereo measurement of {gtsam.Symbol(landmark_key).string()}")
    fx, fy, cx, cy, baseline = camera
    calibration = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, baseline)
    mount = gtsam.Pose3(body_T_left)
    measured = np.asarray(uvv, dtype=float)

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        pose_key, point_key, calibration_key = factor.keys()
        return calibrated_stereo_error(measured, calibration, mount, values.atPose3(pose_key),
                                       values.atPoint3(point_key), values.atVector(calibration_key), jacobians)

    kernel, k, sigma_px, tie_sigma_px = model
    return gtsam.CustomFactor(noise.robust(kernel, noise.stereo_tie(sigma_px, tie_sigma_px), k),
                              [stop_key, landmark_key, CALIBRATION], error)


def calibrated_vo_error(vo_T: gtsam.Pose3, sensitivity: np.ndarray, world_T_a: gtsam.Pose3, world_T_b: gtsam.Pose3,
                        calibration_error: np.ndarray, jacobians: list | None = None) -> np.ndarray:
    """Logmap(m^-1 a_T_b) with m = vo_T Expmap(sensitivity c), the step measured again with the
    pair's error c; [rotation, translation] like GTSAM's BetweenFactor, analytic Jacobians."""
    h_exp = np.zeros((6, 6), order="F")
    correction = gtsam.Pose3.Expmap(sensitivity @ calibration_error, h_exp)
    h_correction = np.zeros((6, 6), order="F")
    m = vo_T.compose(correction, None, h_correction)
    error, d_m, d_a, d_b = factors.between_error(m, world_T_a, world_T_b)
    if jacobians is not None:
        jacobians[0], jacobians[1] = d_a, d_b
        jacobians[2] = d_m @ h_correction @ h_exp @ sensitivity
    return error


def calibrated_vo_factor(key_a: int, key_b: int, vo_T: gtsam.Pose3, covariance: np.ndarray,
                         sensitivity: np.ndarray | None) -> gtsam.CustomFactor:
    """A VO step on its two poses and the pair's calibration error (a step without a sensitivity,
    none known: the plain step, the error's Jacobian zero)."""
    sensitivity = np.zeros((6, len(NAMES))) if sensitivity is None else np.asarray(sensitivity, dtype=float)

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        a, b, c = factor.keys()
        return calibrated_vo_error(vo_T, sensitivity, values.atPose3(a), values.atPose3(b), values.atVector(c),
                                   jacobians)

    return gtsam.CustomFactor(noise.pose_covariance(covariance), [key_a, key_b, CALIBRATION], error)


class StereoCalibrationSettings(Section):
    """[estimator.stereo_calibration]"""

    rotation_sigma_deg: float = Field(0.01, gt=0.0, le=5.0, description="1-sigma of the right camera's rotation "
                                      "left by its calibration, per axis (the project's calibration of the "
                                      "rendered control field: 0.005-0.017 deg)")
    focal_ratio_sigma: float = Field(5e-5, gt=0.0, le=0.05, description="1-sigma of the two cameras' focal ratio "
                                     "left by the calibration (the same calibration: 0.002-0.007 %)")
    focal_scale_sigma: float = Field(3e-4, gt=0.0, le=0.05, description="1-sigma of both focal lengths' common "
                                     "error left by the calibration (the same calibration: fx to 0.54 px of 1,724)")
    baseline_scale_sigma: float = Field(1e-4, gt=0.0, le=0.05, description="1-sigma of the baseline's error left "
                                        "by the calibration, as a ratio (the same calibration: 0.034 mm of 500 mm)")

    def sigmas(self) -> np.ndarray:
        """The prior's 1-sigma of each term, in geometry/calibration_error.py's NAMES order."""
        rotation = np.deg2rad(self.rotation_sigma_deg)
        return np.array([rotation, rotation, rotation, self.focal_ratio_sigma, self.focal_scale_sigma,
                         self.baseline_scale_sigma])


class StereoCalibration(Kind):
    name = "stereo_calibration"
    order = 10
    Settings = StereoCalibrationSettings
    builds_site_stereo = True
    builds_motion = "vo"
    # its VO steps' and site views' factors are Python CustomFactors: a guess, not measured as a
    # ratio (vo_sites' iSAM2 updates on mars_excerpt 20005: 7.9 s in all; docs/performance.md)
    cost = 3.0

    def __init__(self, localizer):
        super().__init__(localizer)
        settings: StereoCalibrationSettings = localizer.estimator.stereo_calibration
        prior = gtsam.noiseModel.Diagonal.Sigmas(settings.sigmas())
        localizer.smoother.add(gtsam.PriorFactorVector(CALIBRATION, np.zeros(len(NAMES)), prior))
        localizer.smoother.insert(CALIBRATION, np.zeros(len(NAMES)), shared=True)

    @classmethod
    def unavailable(cls, traverse) -> str | None:
        # it measures through the stereo pair: the VO's steps or the sites' views
        return VisualOdometry.unavailable(traverse)

    def site_stereo_factor(self):
        return calibrated_stereo_factor

    def motion_factor(self):
        return calibrated_vo_factor

    def site_stereo_pixels(self, uvv: np.ndarray) -> np.ndarray:
        # the error's shifts taken out, to first order (at the measured pixels: a correction of a
        # few tenths of a pixel, not a fit's gradient)
        rig = self.loc.traverse.rig
        uvv = np.asarray(uvv, dtype=float)
        return uvv - pixel_shifts(uvv, rig.wac.fx, rig.wac.cx, rig.wac.cy) @ self.loc.smoother.vector(CALIBRATION)

    def true_values(self, truth, values: gtsam.Values) -> bool:
        # zero where the truth has none (real data, or a simulation with a trusted pair)
        known = truth.kinds.get(self.name, {})
        values.insert(CALIBRATION, np.array([float(known.get(name, 0.0)) for name in NAMES]))
        return True

    def against_truth(self, truth) -> dict[str, float]:
        known = truth.kinds.get(self.name)
        if not known:
            return {}
        estimate = self.loc.smoother.vector(CALIBRATION)
        return {f"{name}_error": float(estimate[i] - known[name]) for i, name in enumerate(NAMES)}

    def counters(self) -> dict:
        estimate = self.loc.smoother.vector(CALIBRATION)
        sigmas = np.sqrt(np.diag(self.loc.smoother.marginal_covariance(CALIBRATION)))
        counts = {}
        for i, name in enumerate(NAMES):
            counts[name], counts[f"{name}_sigma"] = float(estimate[i]), float(sigmas[i])
        return counts
