"""The wheel-slip kind: one slip shared by every odometry step (kinds/wheel_slip.py)."""

import gtsam
import numpy as np
import pytest
from seeds import over_seeds

from pancam_graph.evaluation.consistency import monte_carlo_summary
from pancam_graph.graph.keys import X
from pancam_graph.kinds.wheel_slip import SLIP, slip_odometry_error, slip_odometry_factor

pytestmark = pytest.mark.slow

POSE_A = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, -0.05, 0.02), np.array([3.0, -2.0, 0.3]))
POSE_B = gtsam.Pose3(gtsam.Rot3.Ypr(0.45, -0.03, 0.01), np.array([4.4, -1.5, 0.35]))


def _values(slip: float) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(X(0), POSE_A)
    v.insert(X(1), POSE_B)
    v.insert(SLIP, slip)
    return v


def test_the_true_slip_explains_a_scaled_odometry_step_exactly():
    true = POSE_A.between(POSE_B)
    odometry = gtsam.Pose3(true.rotation(), true.translation() * 1.04)  # wheels turned 4 % too far
    assert np.allclose(slip_odometry_error(odometry, POSE_A, POSE_B, 0.04), 0.0, atol=1e-12)
    assert np.linalg.norm(slip_odometry_error(odometry, POSE_A, POSE_B, 0.0)[3:]) > 0.05


@pytest.mark.parametrize("slip", [-0.02, 0.0, 0.07])
def test_analytic_jacobians_match_central_differences(slip):
    odometry = POSE_A.between(POSE_B).compose(gtsam.Pose3.Expmap(np.array([0.01, -0.02, 0.03, 0.05, -0.04, 0.02])))
    analytic = [None, None, None]
    slip_odometry_error(odometry, POSE_A, POSE_B, slip, analytic)
    eps = 1e-6

    def numeric_pose(which: int) -> np.ndarray:
        cols = []
        for i in range(6):
            d = np.zeros(6)
            d[i] = eps
            poses = [POSE_A, POSE_B]
            plus, minus = list(poses), list(poses)
            plus[which], minus[which] = poses[which].retract(d), poses[which].retract(-d)
            cols.append((slip_odometry_error(odometry, *plus, slip) - slip_odometry_error(odometry, *minus, slip))
                        / (2 * eps))
        return np.column_stack(cols)

    np.testing.assert_allclose(analytic[0], numeric_pose(0), atol=1e-6)
    np.testing.assert_allclose(analytic[1], numeric_pose(1), atol=1e-6)
    d_slip = (slip_odometry_error(odometry, POSE_A, POSE_B, slip + eps)
              - slip_odometry_error(odometry, POSE_A, POSE_B, slip - eps)) / (2 * eps)
    np.testing.assert_allclose(analytic[2][:, 0], d_slip, atol=1e-6)
    # and GTSAM linearizes the factor with them
    factor = slip_odometry_factor(X(0), X(1), odometry, np.eye(6) * 1e-4)
    jacobian = factor.linearize(_values(slip)).jacobian()[0]
    np.testing.assert_allclose(jacobian, np.hstack(analytic) / 1e-2, atol=1e-4)


def test_dead_reckoning_is_consistent_only_with_the_shared_slip(short_scenario):
    """Independent per-step slip noise makes dead reckoning over-confident (its error grows with
    the steps, its covariance with their square root); the shared slip variable does not."""
    configurations = {"independent": ["dead_reckoning"], "shared": ["dead_reckoning", "wheel_slip"]}
    estimator = short_scenario.estimator.model_copy(update={"configurations": configurations})
    scenario = short_scenario.model_copy(update={"estimator": estimator})
    runs = {name: [] for name in configurations}
    for results in over_seeds(scenario, range(20)):
        for name in configurations:
            runs[name].append(results[name].consistency)
    shared, independent = (monte_carlo_summary(runs[name]) for name in ("shared", "independent"))
    assert shared["anees_band"][0] <= shared["anees"] <= shared["anees_band"][1]
    assert shared["efficiency"] <= 1.2
    assert independent["anees"] > shared["anees_band"][1]  # the old model: over-confident
