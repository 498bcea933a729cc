"""The VO's shared direction bias (kinds/vo_scale.py): a step turned sideways and down by the
same small angle at every step is explained exactly by the bias (its factor's Jacobians:
tests/graph/test_factor_jacobians.py)."""

import gtsam
import numpy as np

from pancam_graph.kinds.vo_scale import biased_vo_error, direction_bias

POSE_A = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, -0.05, 0.02), np.array([3.0, -2.0, 0.3]))
POSE_B = gtsam.Pose3(gtsam.Rot3.Ypr(0.45, -0.03, 0.01), np.array([4.4, -1.5, 0.35]))


def test_a_forward_step_turned_by_the_bias_goes_sideways_and_down_by_it():
    turned = direction_bias(0.003, -0.004).rotate(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(turned, [1.0, 0.003, -0.004], atol=2e-5)


def test_the_true_bias_explains_a_biased_step_exactly():
    true = POSE_A.between(POSE_B)
    measured = gtsam.Pose3(true.rotation(), direction_bias(0.004, -0.002).rotate(true.translation()) * 1.01)
    assert np.allclose(biased_vo_error(measured, POSE_A, POSE_B, 0.01, 0.004, -0.002), 0.0, atol=1e-12)
    assert np.linalg.norm(biased_vo_error(measured, POSE_A, POSE_B, 0.01, 0.0, 0.0)[3:]) > 3e-3
