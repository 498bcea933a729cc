"""Compare any estimated trajectory with a reference (trajectory or GPS log): associate by time,
align as asked, and compute the run's metrics."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EvaluationError
from ..records import Trajectory
from .gps_check import antenna_positions
from .metrics import (
    GPS_REFERENCE_STEP_M,
    RPE_DELTA_M,
    Alignment,
    TrajectoryMetrics,
    compare,
    decimated_length,
    fit_alignment,
    path_length,
)

MAX_DT_S = 0.01  # default association tolerance (evo's default)


@dataclass(frozen=True)
class Evaluation:
    estimate: Trajectory  # the matched estimate, aligned to the reference
    reference: Trajectory  # the matched reference
    association: str
    alignment: str
    reference_T_estimate: np.ndarray  # 4x4 transform applied to the estimate
    metrics: TrajectoryMetrics
    lever_arm_m: tuple[float, float, float] | None = None  # the estimate's point: this point of the body

    def as_dict(self) -> dict:
        return {
            "estimate": self.estimate.source,
            "reference": self.reference.source,
            "matched": len(self.reference),
            "association": self.association,
            "alignment": self.alignment,
            "reference_T_estimate": self.reference_T_estimate.tolist(),
            "estimate_point": "body origin" if self.lever_arm_m is None else
            f"GPS antenna at {list(self.lever_arm_m)} m in the body frame",
        }


def at_point_of_body(trajectory: Trajectory, body_point_m: np.ndarray) -> Trajectory:
    """The track of a point fixed in the body (a GPS antenna at its lever arm): what a GPS log
    records, where the trajectory is the body's origin."""
    if trajectory.world_T_body is None:
        raise EvaluationError(f"{trajectory.source}: positions only, no attitude to carry a lever arm")
    return Trajectory(trajectory.source, antenna_positions(trajectory.world_T_body, body_point_m),
                      trajectory.times_s, None, trajectory.geodetic)


def associate(est_times: np.ndarray, ref_times: np.ndarray, max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """For every estimate time the nearest reference time within `max_dt_s`: index arrays
    (estimate, reference). The same rule as evo's `matching_time_indices`."""
    order = np.argsort(ref_times)
    sorted_ref = ref_times[order]
    pos = np.clip(np.searchsorted(sorted_ref, est_times), 1, len(sorted_ref) - 1)
    left, right = sorted_ref[pos - 1], sorted_ref[pos]
    nearest = np.where(np.abs(est_times - left) <= np.abs(right - est_times), pos - 1, pos)
    if len(sorted_ref) == 1:
        nearest = np.zeros(len(est_times), dtype=int)
    keep = np.abs(sorted_ref[nearest] - est_times) <= max_dt_s
    return np.flatnonzero(keep), order[nearest[keep]]


def evaluate_trajectories(
    estimate: Trajectory,
    reference: Trajectory,
    alignment: Alignment = "none",
    max_dt_s: float = MAX_DT_S,
    rpe_delta_m: float = RPE_DELTA_M,
) -> Evaluation:
    """Metrics of `estimate` against `reference`. With an alignment, the estimate is moved by
    the fitted rigid transform before every metric (not only the ATE)."""
    if estimate.times_s is not None and reference.times_s is not None:
        ie, ir = associate(estimate.times_s, reference.times_s, max_dt_s)
        association = f"nearest time within {max_dt_s} s"
        if len(ie) < 2:
            raise EvaluationError(
                f"{estimate.source} and {reference.source}: {len(ie)} poses matched within {max_dt_s} s "
                f"(estimate {estimate.times_s[0]:.3f}..{estimate.times_s[-1]:.3f} s, reference "
                f"{reference.times_s[0]:.3f}..{reference.times_s[-1]:.3f} s); check the time bases or --max-dt")
    else:
        if len(estimate) != len(reference):
            raise EvaluationError(
                f"{estimate.source} ({len(estimate)} poses) and {reference.source} ({len(reference)}): "
                "without times on both sides poses are matched by index, so the counts must agree")
        ie = ir = np.arange(len(estimate))
        association = "by index"
    est, ref = estimate.subset(ie), reference.subset(ir)
    rot, t, applied = fit_alignment(est.positions, ref.positions, alignment)
    ref_T_est = np.eye(4)
    ref_T_est[:3, :3], ref_T_est[:3, 3] = rot, t
    est = Trajectory(est.source, est.positions @ rot.T + t, est.times_s,
                     None if est.world_T_body is None else ref_T_est @ est.world_T_body)
    ref_length = (decimated_length(ref.positions, GPS_REFERENCE_STEP_M) if ref.world_T_body is None
                  else path_length(ref.positions))
    if ref_length <= 0.0:
        raise EvaluationError(f"{reference.source}: the reference stands still over the {len(ref)} matched poses; "
                              "closure, drift and length ratio are relative to the distance travelled")
    both_poses = est.world_T_body is not None and ref.world_T_body is not None
    metrics = compare(est.positions, ref.positions, alignment,
                      est.world_T_body if both_poses else None, ref.world_T_body if both_poses else None,
                      reference_length_m=ref_length, rpe_delta_m=rpe_delta_m)
    return Evaluation(est, ref, association, applied, ref_T_est, metrics)
