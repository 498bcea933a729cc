"""The motion between consecutive stops: stereo VO, or a bridge when VO fails.

Never zero motion (what broke the seed's field result): dead reckoning with its own
covariance when the rover has it, otherwise the previous motion with a wide covariance.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..records import DeadReckoning, SlipPrior, Stop, Traverse
from .stereo_vo import StereoVO, VoResult

# Without any dead reckoning the bridge only says "the rover moved about as before":
# 2 m per axis, 5 deg roll/pitch and 60 deg heading (1 sigma).
_WIDE_SIGMAS = np.array([np.deg2rad(5.0), np.deg2rad(5.0), np.deg2rad(60.0), 2.0, 2.0, 2.0])


@dataclass(frozen=True)
class Motion:
    prev_T_curr: gtsam.Pose3
    covariance: np.ndarray  # [rotation, translation] in the current body frame
    source: Literal["vo", "dead_reckoning", "constant_velocity"]
    vo_inliers: int
    vo_failure: str = ""
    # The raw odometry increment behind a dead-reckoning motion: the wheel-slip kind builds its
    # own factor from it (prev_T_curr above already has the expected slip taken out).
    odometry: DeadReckoning | None = None

    @property
    def bridged(self) -> bool:
        return self.source != "vo"


@dataclass(frozen=True)
class VoMotions:
    """Every stop's motion from the previous one (None for the first), estimated once with this
    estimator configuration: a source that needed them (the site tie points' predictions) hands
    them to the run, which estimates them again only under another configuration."""

    estimator: EstimatorConfig
    motions: tuple[Motion | None, ...]
    seconds: float = 0.0  # what estimating them took

    @staticmethod
    def estimate(traverse: Traverse, estimator: EstimatorConfig) -> VoMotions:
        start = time.perf_counter()
        vo = StereoVO.for_traverse(traverse, estimator)
        motions: list[Motion | None] = [None]
        for k in range(1, len(traverse.stops)):
            motions.append(motion_between(vo, traverse.stops[k - 1], traverse.stops[k], motions[-1],
                                          traverse.wheel_slip))
        return VoMotions(estimator, tuple(motions), time.perf_counter() - start)


def motion_between(vo: StereoVO, prev: Stop, curr: Stop, last: Motion | None, slip: SlipPrior) -> Motion:
    """Stereo VO, bridged by dead reckoning (or constant velocity) where VO fails."""
    return motion_from(vo.estimate(prev.stereo, curr.stereo), curr, last, slip)


def motion_from(result: VoResult, curr: Stop, last: Motion | None, slip: SlipPrior) -> Motion:
    """The VO's motion to stop `curr`, bridged where it failed."""
    if result.ok:
        return Motion(result.prev_T_curr, result.covariance, "vo", result.inliers)
    return dead_reckoning_motion(curr, last, slip, result.inliers, result.reason)


def dead_reckoning_motion(curr: Stop, last: Motion | None, slip: SlipPrior, vo_inliers: int = 0,
                          vo_failure: str = "") -> Motion:
    """The stop's wheel odometry + IMU increment with the expected slip taken out, and its own
    covariance widened along the drive by the slip's uncertainty (as if it were independent per
    step, which it is not: over many steps only the wheel-slip kind is honest); constant velocity
    with a wide covariance when the stop has none."""
    if curr.dead_reckoning is not None:
        dr = curr.dead_reckoning
        t = dr.prev_T_curr[:3, 3]
        corrected = gtsam.Pose3(gtsam.Rot3(dr.prev_T_curr[:3, :3]), t / (1.0 + slip.mean))
        # translation sigma along the drive, expressed in the current body frame (GTSAM's)
        along = dr.prev_T_curr[:3, :3].T @ t / (1.0 + slip.mean) * slip.sigma
        covariance = dr.covariance.copy()
        covariance[3:, 3:] += np.outer(along, along)
        return Motion(corrected, covariance, "dead_reckoning", vo_inliers, vo_failure, odometry=dr)
    guess = last.prev_T_curr if last is not None else gtsam.Pose3()
    return Motion(guess, np.diag(_WIDE_SIGMAS**2), "constant_velocity", vo_inliers, vo_failure)
