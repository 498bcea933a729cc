"""One scale error shared by every stereo VO step of the traverse.

A stereo baseline known to 0.5 % makes every VO step 0.5 % too long or too short, the same
way at every step (the dissertation's field VO "came out shorter than GPS"); treated as independent per
step, that error grows with N while the covariance grows with sqrt(N). Here S(1) is a variable
with prior N(0, [estimator.vo_scale] sigma), and every VO between factor becomes a factor on its two poses
and S(1) (the wheel-slip kind's factor: measured translation = (1 + scale) x true); GPS or
site tie points, where present, estimate it.

Real VO is also biased in direction: on KITTI frames every step drifts the same way sideways and
down (docs/frontend.md, "The VO error model on real images"). With `direction_sigma` set, two
more shared variables, S(2) lateral and S(3) vertical, turn every VO step's translation the same
small angle: measured translation = (1 + scale) x D x true, D the rotation that takes the body's
forward axis to (1, lateral, vertical).
"""

from __future__ import annotations

import gtsam
import numpy as np
from pydantic import Field

from ..graph import keys, noise
from .base import Kind, Section
from .motion import VisualOdometry
from .wheel_slip import slip_odometry_error, slip_odometry_factor

VO_SCALE, VO_LATERAL, VO_VERTICAL = keys.shared("vo_scale", 3)
_STEP = 1e-6  # central differences in the direction angles (rad): the error is smooth in them


def vo_scale_factor(key_a: int, key_b: int, vo_T: gtsam.Pose3, covariance, sensitivity=None):
    # (a VO factor's calibration sensitivity: this kind models no calibration)
    return slip_odometry_factor(key_a, key_b, vo_T, covariance, scale_key=VO_SCALE)


def direction_bias(lateral: float, vertical: float) -> gtsam.Rot3:
    """The rotation that takes the body's forward axis (x) to (1, lateral, vertical), to first order."""
    return gtsam.Rot3.Expmap(np.array([0.0, -vertical, lateral]))


def biased_vo_error(vo_T: gtsam.Pose3, world_T_a: gtsam.Pose3, world_T_b: gtsam.Pose3, scale: float,
                    lateral: float, vertical: float, jacobians: list | None = None) -> np.ndarray:
    """The VO step's error with its translation unturned by the direction bias and unscaled;
    [rotation, translation] like GTSAM's BetweenFactor. Jacobians with respect to the poses and
    the scale are analytic (slip_odometry_error), to the two angles by central differences."""
    unturned = gtsam.Pose3(vo_T.rotation(), direction_bias(lateral, vertical).unrotate(vo_T.translation()))
    error = slip_odometry_error(unturned, world_T_a, world_T_b, scale, jacobians)
    if jacobians is not None:
        for slot, (dl, dv) in ((3, (_STEP, 0.0)), (4, (0.0, _STEP))):
            plus = biased_vo_error(vo_T, world_T_a, world_T_b, scale, lateral + dl, vertical + dv)
            minus = biased_vo_error(vo_T, world_T_a, world_T_b, scale, lateral - dl, vertical - dv)
            jacobians[slot] = ((plus - minus) / (2 * _STEP)).reshape(6, 1)
    return error


def biased_vo_factor(key_a: int, key_b: int, vo_T: gtsam.Pose3, covariance: np.ndarray,
                     sensitivity=None) -> gtsam.CustomFactor:
    """A VO step on its two poses, the shared scale and the shared direction bias."""

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        a, b, s, lat, vert = factor.keys()
        return biased_vo_error(vo_T, values.atPose3(a), values.atPose3(b), values.atDouble(s),
                               values.atDouble(lat), values.atDouble(vert), jacobians)

    return gtsam.CustomFactor(noise.pose_covariance(covariance), [key_a, key_b, VO_SCALE, VO_LATERAL, VO_VERTICAL],
                              error)


class VoScaleSettings(Section):
    """[estimator.vo_scale]"""

    sigma: float = Field(0.01, gt=0.0, lt=0.5, description="1-sigma scale error shared by every VO step (the "
                         "stereo baseline's calibration)")
    direction_sigma: float = Field(0.0, ge=0.0, lt=0.1, description="1-sigma direction bias shared by every VO "
                                   "step, lateral and vertical (rad); 0: none")


class VoScale(Kind):
    name = "vo_scale"
    order = 6
    Settings = VoScaleSettings
    unavailable = staticmethod(VisualOdometry.unavailable)
    builds_motion = "vo"

    def __init__(self, localizer):
        super().__init__(localizer)
        model = gtsam.noiseModel.Isotropic.Sigma(1, localizer.estimator.vo_scale.sigma)
        localizer.smoother.add(gtsam.PriorFactorDouble(VO_SCALE, 0.0, model))
        localizer.smoother.insert(VO_SCALE, 0.0, shared=True)
        direction_sigma = localizer.estimator.vo_scale.direction_sigma
        if direction_sigma > 0:
            angle = gtsam.noiseModel.Isotropic.Sigma(1, direction_sigma)
            for key in (VO_LATERAL, VO_VERTICAL):
                localizer.smoother.add(gtsam.PriorFactorDouble(key, 0.0, angle))
                localizer.smoother.insert(key, 0.0, shared=True)
        self.direction = direction_sigma > 0

    def motion_factor(self):
        return biased_vo_factor if self.direction else vo_scale_factor

    def true_values(self, truth, values: gtsam.Values) -> bool:
        # the calibration's scale error: zero in simulation, unknown on real data, where the bound
        # is linearized at its prior mean (the factor is nearly linear in it)
        values.insert(VO_SCALE, 0.0)
        if self.direction:
            values.insert(VO_LATERAL, 0.0)
            values.insert(VO_VERTICAL, 0.0)
        return True

    def counters(self) -> dict:
        scale = self.loc.smoother.estimate_double(VO_SCALE)
        sigma = float(self.loc.smoother.marginal_covariance(VO_SCALE)[0, 0] ** 0.5)
        counts = {"vo_scale": scale, "vo_scale_sigma": sigma}
        if self.direction:
            for name, key in (("vo_lateral", VO_LATERAL), ("vo_vertical", VO_VERTICAL)):
                counts[name] = self.loc.smoother.estimate_double(key)
                counts[f"{name}_sigma"] = float(self.loc.smoother.marginal_covariance(key)[0, 0] ** 0.5)
        return counts
