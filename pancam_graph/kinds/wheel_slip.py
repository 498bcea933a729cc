"""Wheel slip as one unknown shared by every odometry step of the traverse.

Slip is a bias of the terrain and the load, the same along a drive: odometry distance =
(1 + slip) x true distance. Treated as independent noise per step it makes dead reckoning
over-confident (its error grows with N, its covariance with sqrt(N); ANEES 11.5 over 30
seeds of denver_trail). Here S(0) is a variable with the traverse's prior, and every
odometry increment becomes a `slip_odometry_factor` on its two poses and S(0): the steps
then share their slip error through S(0), and GPS or VO, where present, estimate it.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..graph import factors, keys, noise
from .base import Kind
from .motion import DeadReckoningMotion

(SLIP,) = keys.shared("wheel_slip", 1)


def slip_odometry_error(odom_T: gtsam.Pose3, world_T_a: gtsam.Pose3, world_T_b: gtsam.Pose3, slip: float,
                        jacobians: list | None = None) -> np.ndarray:
    """Logmap(m^-1 a_T_b), m the odometry increment with its translation divided by (1 + slip);
    [rotation, translation] like GTSAM's BetweenFactor. Fills analytic Jacobians with respect to
    world_T_a, world_T_b (tangent spaces) and slip when `jacobians` is given."""
    scale = 1.0 / (1.0 + slip)
    m = gtsam.Pose3(odom_T.rotation(), odom_T.translation() * scale)
    error, d_m, d_a, d_b = factors.between_error(m, world_T_a, world_T_b)
    if jacobians is not None:
        # m moves along its own translation: in m's tangent space (body frame) that is R^T dt
        dm_dslip = np.zeros(6)
        dm_dslip[3:] = odom_T.rotation().matrix().T @ (-odom_T.translation() * scale**2)
        jacobians[0], jacobians[1] = d_a, d_b
        jacobians[2] = (d_m @ dm_dslip).reshape(6, 1)
    return error


def slip_odometry_factor(key_a: int, key_b: int, odom_T: gtsam.Pose3, covariance: np.ndarray,
                         scale_key: int = SLIP) -> gtsam.CustomFactor:
    """An odometry increment between poses key_a and key_b whose distance is scaled by the
    traverse's slip (the variable `scale_key`, S(0)); `covariance` is the step's own noise
    ([rotation, translation])."""

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        a, b, s = factor.keys()
        return slip_odometry_error(odom_T, values.atPose3(a), values.atPose3(b), values.atDouble(s), jacobians)

    return gtsam.CustomFactor(noise.pose_covariance(covariance), [key_a, key_b, scale_key], error)


class WheelSlip(Kind):
    name = "wheel_slip"
    order = 2
    cost = 2.0
    unavailable = staticmethod(DeadReckoningMotion.unavailable)  # it scales the odometry steps
    builds_motion = "odometry"

    def __init__(self, localizer):
        super().__init__(localizer)
        prior = localizer.traverse.wheel_slip
        model = gtsam.noiseModel.Isotropic.Sigma(1, prior.sigma)
        localizer.smoother.add(gtsam.PriorFactorDouble(SLIP, prior.mean, model))
        localizer.smoother.insert(SLIP, prior.mean, shared=True)

    def motion_factor(self):
        return slip_odometry_factor

    def true_values(self, truth, values: gtsam.Values) -> bool:
        if truth.wheel_slip is None:
            return False
        values.insert(SLIP, float(truth.wheel_slip))
        return True

    def counters(self) -> dict:
        slip = self.loc.smoother.estimate_double(SLIP)
        sigma = float(np.sqrt(self.loc.smoother.marginal_covariance(SLIP)[0, 0]))
        return {"wheel_slip": slip, "wheel_slip_sigma": sigma}
