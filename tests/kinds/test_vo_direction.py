"""The VO's shared direction bias (kinds/vo_scale.py): a step turned sideways and down by the
same small angle at every step is explained exactly by the bias, and GTSAM linearizes the
factor with Jacobians that match numerical derivatives."""

import gtsam
import numpy as np
import pytest

from pancam_graph.graph.keys import X
from pancam_graph.kinds.vo_scale import (
    VO_LATERAL,
    VO_SCALE,
    VO_VERTICAL,
    biased_vo_error,
    biased_vo_factor,
    direction_bias,
)

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


@pytest.mark.parametrize("bias", [(0.0, 0.0, 0.0), (0.02, 0.01, -0.03)])
def test_gtsam_linearizes_it_with_jacobians_of_numerical_derivatives(bias):
    vo_T = POSE_A.between(POSE_B).compose(gtsam.Pose3.Expmap(np.array([0.01, -0.02, 0.03, 0.05, -0.04, 0.02])))
    values = gtsam.Values()
    values.insert(X(0), POSE_A)
    values.insert(X(1), POSE_B)
    for key, value in zip((VO_SCALE, VO_LATERAL, VO_VERTICAL), bias, strict=True):
        values.insert(key, value)
    factor = biased_vo_factor(X(0), X(1), vo_T, np.eye(6))
    analytic = factor.linearize(values).jacobian()[0]
    eps = 1e-6
    columns = []
    for key in factor.keys():
        dim = 6 if gtsam.Symbol(key).chr() == ord("x") else 1
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = eps
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            plus.update(key, values.atPose3(key).retract(d) if dim == 6 else values.atDouble(key) + eps)
            minus.update(key, values.atPose3(key).retract(-d) if dim == 6 else values.atDouble(key) - eps)
            columns.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / (2 * eps))
    np.testing.assert_allclose(analytic, np.column_stack(columns), atol=1e-6)
