"""The tie-point gate: merged site triangulations, relative-pose covariance from a joint
marginal, and the Mahalanobis disagreement being chi-square(3) for true ties."""

import gtsam
import numpy as np
import pytest

from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph.keys import X
from pancam_graph.graph.tie_gate import AGREEMENT_GATE, RelativePose, SitePoint, disagreement2, site_points

RIG = rig_preset("exomars")
SIGMA_PX = 0.3


def _view(mount: gtsam.Pose3, p_body: np.ndarray, rng, sigma=SIGMA_PX) -> np.ndarray:
    """Rectified (u_left, u_right, v) of a body-frame point from the left camera at `mount`."""
    p = mount.transformTo(p_body)
    cam = RIG.wac
    u = cam.fx * p[0] / p[2] + cam.cx
    v = cam.fy * p[1] / p[2] + cam.cy
    return np.array([u, u - cam.fx * RIG.baseline_m / p[2], v]) + rng.normal(0.0, sigma, 3)


def site_point(views, rig, sigma_px):
    return site_points({5: views}, rig, sigma_px)[5]


def test_site_point_merges_agreeing_views_and_refuses_disagreeing_ones():
    rng = np.random.default_rng(1)
    point = np.array([18.0, 3.0, -1.2])
    mounts = [RIG.body_T_left(np.deg2rad(p), np.deg2rad(-6.0)) for p in (0.0, 12.0)]
    single = site_point([(mounts[0], _view(mounts[0], point, rng))], RIG, SIGMA_PX)
    both = site_point([(m, _view(m, point, rng)) for m in mounts], RIG, SIGMA_PX)
    # two independent views: the merged covariance is about half of one view's
    assert np.trace(both.cov_body) == pytest.approx(0.5 * np.trace(single.cov_body), rel=0.25)
    assert np.linalg.norm(both.p_body - point) < 3 * np.sqrt(np.trace(both.cov_body))
    false = np.array([200.0, 170.0, 400.0])  # random pixels: another point entirely
    assert site_point([(mounts[0], _view(mounts[0], point, rng)), (mounts[1], false)], RIG, SIGMA_PX) is None
    behind = np.array([300.0, 310.0, 400.0])  # negative disparity
    assert site_point([(mounts[0], behind)], RIG, SIGMA_PX) is None
    # one site, many tracks at once: each merged on its own
    many = site_points({1: [(mounts[0], _view(mounts[0], point, rng))], 2: [(mounts[0], behind)],
                        3: [(m, _view(m, point + 1.0, rng)) for m in mounts]}, RIG, SIGMA_PX)
    assert many[2] is None and np.linalg.norm(many[1].p_body - point) < 1.0
    assert np.linalg.norm(many[3].p_body - point - 1.0) < 1.0


def test_relative_pose_covariance_of_a_chain_is_its_between_factor():
    """X0 -- between(cov) -- X1: whatever the prior on X0, X0_T_X1 has exactly that covariance."""
    rng = np.random.default_rng(2)
    a = rng.normal(size=(6, 6)) * 0.01
    cov = a @ a.T + np.diag([1e-5, 1e-5, 2e-5, 1e-3, 1e-3, 2e-3])
    x0 = gtsam.Pose3(gtsam.Rot3.Ypr(0.7, 0.02, -0.01), np.array([5.0, -3.0, 1.0]))
    motion = gtsam.Pose3(gtsam.Rot3.Ypr(0.1, 0.0, 0.01), np.array([1.5, 0.2, 0.0]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), x0, gtsam.noiseModel.Isotropic.Sigma(6, 0.3)))
    graph.add(gtsam.BetweenFactorPose3(X(0), X(1), motion, gtsam.noiseModel.Gaussian.Covariance(cov)))
    values = gtsam.Values()
    values.insert(X(0), x0)
    values.insert(X(1), x0.compose(motion))
    joint = gtsam.Marginals(graph, values).jointMarginalCovariance([X(0), X(1)])
    full = np.block([[joint.at(X(0), X(0)), joint.at(X(0), X(1))], [joint.at(X(1), X(0)), joint.at(X(1), X(1))]])
    relative = RelativePose.from_joint(x0, x0.compose(motion), full)
    np.testing.assert_allclose(relative.covariance, cov, rtol=1e-6, atol=1e-12)
    assert relative.a_T_b.equals(motion, 1e-9)


def test_true_ties_are_chi_square_3_and_false_matches_fail():
    """Site b 30 m on with an uncertain relative pose: for true ties, the disagreement of the
    two triangulations (noise drawn from the covariances the gate assumes) is chi-square(3);
    random-pixel false matches almost never pass."""
    rng = np.random.default_rng(3)
    rel_cov = np.diag(np.square([0.002, 0.002, 0.005, 0.05, 0.05, 0.03]))
    true_a_T_b = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([30.0, 4.0, 0.5]))
    mount = RIG.body_T_left(0.0, np.deg2rad(-6.0))
    d2_true, d2_false = [], []
    for _ in range(400):
        # a point seen from both sites, in front of both: 5-40 m ahead of a, within the FOV
        p_a = np.array([rng.uniform(35.0, 55.0), rng.uniform(-6.0, 6.0), rng.uniform(-1.6, -0.6)])
        p_b = true_a_T_b.transformTo(p_a)
        error = gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), rel_cov))
        believed = RelativePose(true_a_T_b.compose(error), rel_cov)
        at_a = site_point([(mount, _view(mount, p_a, rng))], RIG, SIGMA_PX)
        at_b = site_point([(mount, _view(mount, p_b, rng))], RIG, SIGMA_PX)
        d2_true.append(disagreement2(at_a, at_b, believed))
        u = rng.uniform(0, RIG.wac.width - 1)
        false = np.array([u, u - rng.uniform(0.5, 60.0), rng.uniform(0, RIG.wac.height - 1)])
        wrong = site_point([(mount, false)], RIG, SIGMA_PX)
        if wrong is not None:
            d2_false.append(disagreement2(at_a, wrong, believed))
    d2_true = np.array(d2_true)
    assert np.mean(d2_true) == pytest.approx(3.0, rel=0.15)
    assert np.mean(d2_true > AGREEMENT_GATE) < 0.01
    assert len(d2_false) > 300 and np.mean(np.array(d2_false) <= AGREEMENT_GATE) < 0.01


def test_site_point_of_one_view_is_its_triangulation():
    rng = np.random.default_rng(4)
    mount = RIG.body_T_left(np.deg2rad(30.0), np.deg2rad(-22.0))
    point = mount.transformFrom(np.array([1.0, 0.5, 12.0]))
    sp = site_point([(mount, _view(mount, point, rng, sigma=0.0))], RIG, SIGMA_PX)
    assert isinstance(sp, SitePoint)
    np.testing.assert_allclose(sp.p_body, point, atol=1e-9)


def test_composed_relative_pose_covariance_matches_sampled_chains():
    """RelativePose.compose (GTSAM's compose Jacobians) against 4000 sampled three-step chains."""
    rng = np.random.default_rng(3)
    steps = [(gtsam.Pose3(gtsam.Rot3.Ypr(0.1 * k, 0.02, -0.01), np.array([1.5, 0.2 * k, 0.05])),
              np.diag([1e-4, 2e-4, 4e-4, 1e-3, 2e-3, 5e-4]) * (k + 1)) for k in range(3)]
    composed = RelativePose.compose(steps)
    errors = []
    for _ in range(4000):
        chain = gtsam.Pose3()
        for step, cov in steps:
            chain = chain.compose(step.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov))))
        errors.append(gtsam.Pose3.Logmap(composed.a_T_b.between(chain)))
    sampled = np.cov(np.array(errors).T)
    assert np.allclose(np.diag(sampled), np.diag(composed.covariance), rtol=0.1)


def test_composed_calibration_sensitivity_is_the_chain_measured_through_an_erring_pair():
    """Each step measured through a pair off by c is the true one times Expmap(-S c)
    (Motion.calibration_sensitivity); the composed chain's change is compose's sensitivity times
    c, to first order, and a step that knows no sensitivity adds none."""
    rng = np.random.default_rng(7)
    truth = [gtsam.Pose3(gtsam.Rot3.Ypr(0.05 * k, 0.01, -0.02), np.array([1.5, 0.1 * k, 0.03])) for k in range(40)]
    sensitivities = [rng.normal(0.0, 50.0, (6, 6)) for _ in truth]
    sensitivities[7] = None  # a bridged step
    c = rng.normal(0.0, 1e-6, 6)
    measured = [step if s is None else step.compose(gtsam.Pose3.Expmap(-s @ c))
                for step, s in zip(truth, sensitivities, strict=True)]
    composed = RelativePose.compose([(m, np.eye(6) * 1e-6) for m in measured], sensitivities)
    exact = RelativePose.compose([(t, np.eye(6) * 1e-6) for t in truth]).a_T_b
    change = gtsam.Pose3.Logmap(exact.between(composed.a_T_b))
    predicted = composed.calibration_sensitivity @ c
    assert np.linalg.norm(predicted) > 1e-3  # a change worth measuring: 40 steps of 50 units a term
    np.testing.assert_allclose(change, predicted, rtol=0.0, atol=2e-3 * np.linalg.norm(predicted))
    assert RelativePose.compose([(m, np.eye(6)) for m in measured]).calibration_sensitivity is None
