"""The numpy two-stop adjustment against the GTSAM graph it stands for (two GenericStereoFactor3D
a point, the previous pose held by a tight prior), and its Jacobians against numerical ones."""

import gtsam
import numpy as np
import pytest

from pancam_graph.frontend.two_stop_adjustment import StereoIntrinsics, _Problem, adjust_two_stops
from pancam_graph.geometry.rig import rig_preset, triangulate_rectified
from pancam_graph.graph.keys import L, X

SIGMA_PX = 0.3


def _pair(seed: int, n: int = 60):
    """Stereo pixels of n points seen from two stops 1.5 m apart (with a turn), with pixel noise;
    the points triangulated at the first stop; the true prev_T_curr and the rig."""
    rng = np.random.default_rng(seed)
    rig = rig_preset("exomars")
    intrinsics = StereoIntrinsics.of(rig.stereo_calibration())
    # the left camera 1.9 m up, looking ahead (x forward in the body) and 20 deg down
    body_T_left = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2 - np.deg2rad(20.0)), [0.0, 0.1, 1.9])
    prev_T_curr = gtsam.Pose3(gtsam.Rot3.Ypr(np.deg2rad(4.0), 0.003, -0.002), [1.5, 0.1, 0.02])
    cam = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-1, 2, n), rng.uniform(3, 20, n)])
    curr_cam_T_prev_cam = (body_T_left.inverse() * prev_T_curr.inverse() * body_T_left)
    cam1 = np.array([curr_cam_T_prev_cam.transformFrom(p) for p in cam])
    a = intrinsics.project(cam) + rng.normal(0, SIGMA_PX, (n, 3))
    b = intrinsics.project(cam1) + rng.normal(0, SIGMA_PX, (n, 3))
    b[:3] += 25.0  # three outliers
    points = triangulate_rectified(a[:, 0], a[:, 1], a[:, 2], rig.wac, rig.baseline_m)
    return a, b, points, prev_T_curr, intrinsics, body_T_left, rig


def _gtsam_adjustment(a, b, points, guess, rig, body_T_left):
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    values.insert(X(0), gtsam.Pose3())
    values.insert(X(1), guess)
    calibration = rig.stereo_calibration()
    model = gtsam.noiseModel.Isotropic.Sigma(3, SIGMA_PX)
    for j in range(len(a)):
        graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*a[j]), model, X(0), L(j), calibration, body_T_left))
        graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*b[j]), model, X(1), L(j), calibration, body_T_left))
        values.insert(L(j), body_T_left.transformFrom(points[j]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    cov = gtsam.Marginals(graph, result).marginalCovariance(X(1))
    chi2 = np.array([2 * (graph.at(1 + 2 * j).error(result) + graph.at(2 + 2 * j).error(result))
                     for j in range(len(a))])
    return result.atPose3(X(1)), cov, chi2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_gtsam_optimum_marginal_and_residuals(seed):
    a, b, points, truth, intrinsics, body_T_left, rig = _pair(seed)
    guess = truth.compose(gtsam.Pose3(gtsam.Rot3.Rz(0.02), [0.1, -0.05, 0.03]))
    ours = adjust_two_stops(a, b, points, guess, intrinsics, body_T_left, SIGMA_PX)
    pose, cov, chi2 = _gtsam_adjustment(a, b, points, guess, rig, body_T_left)
    # ours stops at GTSAM's default tolerance (relative decrease 1e-5), the reference runs on
    d = pose.localCoordinates(ours.prev_T_curr)
    assert d @ np.linalg.solve(cov, d) < 1e-3  # within 0.03 sigma
    assert np.abs(ours.covariance - cov).max() < 1e-4 * np.abs(cov).max()
    np.testing.assert_allclose(ours.point_chi2, chi2, rtol=1e-3, atol=1e-2)  # the gate is 16.8
    assert np.all(ours.point_chi2[:3] > 100.0)  # the outliers stand out
    # and the estimate is near the truth it was simulated from (outliers included)
    assert np.linalg.norm(ours.prev_T_curr.translation() - truth.translation()) < 0.1


def test_jacobians_match_numerical_derivatives():
    a, b, points, truth, intrinsics, body_T_left, _ = _pair(5, n=8)
    problem = _Problem(a, b, intrinsics, body_T_left)
    here = problem.evaluate(truth, points)
    H_xx, g_x, H_pp, H_xp, g_p = problem.normal_equations(here)
    # g = J^T r: compare the gradient of the cost (= 2 g) with central differences
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        up = problem.evaluate(truth.compose(gtsam.Pose3.Expmap(d)), points).cost
        down = problem.evaluate(truth.compose(gtsam.Pose3.Expmap(-d)), points).cost
        assert (up - down) / (2 * eps) == pytest.approx(2 * g_x[i], rel=1e-4, abs=1e-4)
    for j in range(len(points)):
        for i in range(3):
            moved = points.copy()
            moved[j, i] += eps
            up = problem.evaluate(truth, moved).cost
            moved[j, i] -= 2 * eps
            down = problem.evaluate(truth, moved).cost
            assert (up - down) / (2 * eps) == pytest.approx(2 * g_p[j, i], rel=1e-4, abs=1e-4)
    assert np.all(np.linalg.eigvalsh(H_pp) > 0)
    assert H_xp.shape == (len(points), 6, 3)


def test_point_behind_the_camera_is_indeterminate():
    a, b, points, truth, intrinsics, body_T_left, _ = _pair(3, n=10)
    points[4, 2] = -2.0
    assert adjust_two_stops(a, b, points, truth, intrinsics, body_T_left, SIGMA_PX) is None


def test_the_calibration_sensitivity_is_the_adjustment_solved_again_with_the_true_pair():
    """Each calibration term at a realistic size (0.01 deg, 0.01-0.03 %, the baseline 0.1 %): the
    pixels corrected by its shifts and the step solved again moves as the sensitivity says
    (measured within 0.3 % of the larger moves; the turn about the vertical pitches the step by
    217 urad for 2e-4 rad)."""
    from pancam_graph.geometry.calibration_error import pixel_shifts

    a, b, points, truth, intrinsics, body_T_left, _ = _pair(0)
    a, b, points = a[3:], b[3:], points[3:]  # without the outliers: the chi-square gate keeps them out anyway
    solution = adjust_two_stops(a, b, points, truth, intrinsics, body_T_left, SIGMA_PX)
    for k, size in enumerate([2e-4, 2e-4, 2e-4, 1e-4, 3e-4, 1e-3]):
        c = np.zeros(6)
        c[k] = size
        again = adjust_two_stops(*(px - pixel_shifts(px, intrinsics.fx, intrinsics.cx, intrinsics.cy) @ c
                                   for px in (a, b)), points, solution.prev_T_curr, intrinsics, body_T_left,
                                 SIGMA_PX)
        moved = solution.prev_T_curr.localCoordinates(again.prev_T_curr)
        predicted = solution.calibration_sensitivity @ c
        assert np.abs(moved).max() > 2e-5  # each term moves the step
        np.testing.assert_allclose(predicted, moved, atol=0.01 * np.abs(moved).max())
    assert solution.calibration_sensitivity[1, 1] == pytest.approx(-1.09, abs=0.05)  # pitch per rad about vertical
