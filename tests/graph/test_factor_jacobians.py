"""Every factor the graph uses: analytic Jacobians (GTSAM's linearization) against central
differences of the whitened error on the manifold."""

import gtsam
import numpy as np
import pytest

from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph import factors, noise
from pancam_graph.graph.keys import L, X

RIG = rig_preset("exomars")
POSE_A = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, -0.05, 0.02), np.array([3.0, -2.0, 0.3]))
POSE_B = gtsam.Pose3(gtsam.Rot3.Ypr(0.45, -0.03, 0.01), np.array([4.4, -1.5, 0.35]))


# poses, landmarks, shared scalars (slip, VO scale and bias), errors neighbouring registrations share
_DIM = {ord("x"): 6, ord("l"): 3, ord("s"): 1, ord("e"): 4}


def _perturb(values: gtsam.Values, key: int, delta: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(values)
    kind = gtsam.Symbol(key).chr()
    if kind == ord("x"):
        out.update(key, values.atPose3(key).retract(delta))
    elif kind == ord("s"):
        out.update(key, values.atDouble(key) + float(delta[0]))
    elif kind == ord("e"):
        out.update(key, values.atVector(key) + delta)
    else:
        out.update(key, values.atPoint3(key) + delta)
    return out


def _check(factor, values, eps=1e-6, rtol=1e-5):
    model = factor.noiseModel()

    def whitened(v):
        return model.whiten(factor.unwhitenedError(v))

    analytic = factor.linearize(values).jacobian()[0]
    numeric = []
    for key in factor.keys():
        dim = _DIM[gtsam.Symbol(key).chr()]
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = eps
            numeric.append((whitened(_perturb(values, key, d)) - whitened(_perturb(values, key, -d))) / (2 * eps))
    numeric = np.column_stack(numeric)
    scale = np.abs(analytic).max()
    np.testing.assert_allclose(analytic, numeric, atol=rtol * scale)


def _values(point=None):
    v = gtsam.Values()
    v.insert(X(0), POSE_A)
    v.insert(X(1), POSE_B)
    if point is not None:
        v.insert(L(7), point)
    return v


def test_prior_jacobian():
    f = factors.start_prior(POSE_B.matrix(), np.array([0.01, 0.01, 0.02, 0.1, 0.1, 0.1]))
    _check(f, _values())


def test_motion_jacobian_with_full_covariance():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6)) * 0.01
    cov = a @ a.T + np.eye(6) * 1e-4
    f = factors.motion(0, 1, POSE_A.between(POSE_B).compose(gtsam.Pose3.Expmap(np.full(6, 0.01))), cov)
    _check(f, _values())


@pytest.mark.parametrize("pan,tilt", [(0.0, -0.2), (2.1, -0.1), (-1.2, 0.3)])
def test_stereo_jacobian_with_mast_mount(pan, tilt):
    mount = RIG.body_T_left(pan, tilt)
    world_cam = POSE_A.compose(mount)
    point = world_cam.transformFrom(np.array([0.8, 0.3, 14.0]))
    cam = gtsam.StereoCamera(world_cam, RIG.stereo_calibration())
    measured = cam.project(point).vector() + np.array([0.7, -0.4, 0.5])
    f = factors.stereo(0, 7, measured, RIG.stereo_calibration(), mount, noise.stereo_pixels(0.3))
    _check(f, _values(point))


def test_hrc_projection_jacobian():
    mount = RIG.body_T_hrc(0.9, -0.08)
    point = POSE_A.compose(mount).transformFrom(np.array([0.3, -0.2, 30.0]))
    cam = gtsam.PinholeCameraCal3_S2(POSE_A.compose(mount), RIG.hrc.gtsam_calibration())
    measured = cam.project(point) + np.array([2.0, -1.5])
    f = factors.projection(0, 7, measured, RIG.hrc.gtsam_calibration(), mount, noise.image_pixels(0.3))
    _check(f, _values(point))


def test_gps_lever_arm_jacobian():
    f = factors.gps(1, np.array([4.0, -1.0, 2.5]), np.array([0.1, -0.2, 1.8]), noise.gps_position(2.0, 3.0))
    _check(f, _values())


def test_gps_factor_uses_the_lever_arm():
    lever = np.array([0.0, 0.0, 1.8])
    antenna = POSE_A.transformFrom(lever)
    f = factors.gps(0, antenna, lever, noise.gps_position(2.0, 3.0))
    assert f.error(_values()) == pytest.approx(0.0, abs=1e-18)


def test_landmark_anchor_jacobian_and_its_relative_measurement():
    p_body = np.array([10.0, 4.0, 1.0])
    f = factors.landmark_anchor(0, 7, p_body)
    v = gtsam.Values()
    v.insert(X(0), POSE_A)
    # GTSAM differentiates the bearing in the predicted direction's tangent basis but measures the
    # error in the measured one's: exact at zero bearing error, first order away from it (0.2 %
    # at 3 mrad). Exact where it matters, then close nearby.
    v.insert(L(7), POSE_A.transformFrom(p_body * 1.1))
    _check(f, v)
    v.update(L(7), POSE_A.transformFrom(p_body + np.array([0.02, -0.03, 0.2])))
    _check(f, v, rtol=5e-3)
    # Zero error wherever the site is, as long as the landmark moves with it: no world information.
    moved = gtsam.Values()
    moved.insert(X(0), POSE_B)
    moved.insert(L(7), POSE_B.transformFrom(p_body))
    assert f.error(moved) == pytest.approx(0.0, abs=1e-18)
    # 3 m along the line of sight is one sigma.
    along = gtsam.Values()
    along.insert(X(0), POSE_A)
    along.insert(L(7), POSE_A.transformFrom(p_body * (1 + 3.0 / np.linalg.norm(p_body))))
    assert 2 * f.error(along) == pytest.approx(1.0, rel=1e-9)


@pytest.mark.parametrize("bias", [(0.0, 0.0, 0.0), (0.02, 0.01, -0.03)])
def test_vo_step_with_shared_scale_and_direction_bias_jacobian(bias):
    from pancam_graph.kinds.vo_scale import VO_LATERAL, VO_SCALE, VO_VERTICAL, biased_vo_factor

    vo_T = POSE_A.between(POSE_B).compose(gtsam.Pose3.Expmap(np.array([0.01, -0.02, 0.03, 0.05, -0.04, 0.02])))
    values = _values()
    for key, value in zip((VO_SCALE, VO_LATERAL, VO_VERTICAL), bias, strict=True):
        values.insert(key, value)
    _check(biased_vo_factor(X(0), X(1), vo_T, np.diag([1e-6] * 3 + [1e-4] * 3)), values)


@pytest.mark.parametrize("bias", [(0.0, 0.0, 0.0, 0.0), (2.5, -1.7, 0.8, 0.004)])
@pytest.mark.parametrize("shared", [0, 2])
def test_orbital_registration_on_pose_map_bias_and_shared_errors_jacobian(bias, shared):
    from pancam_graph.graph.keys import E
    from pancam_graph.kinds.orbital import bias_keys, orbital_factor

    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 4)) * 0.1
    keys = tuple(E(k) for k in range(shared))
    f = orbital_factor(0, 1, np.array([5.0, -0.8, 0.2, 0.5]), a @ a.T + np.eye(4) * 0.01, keys)
    values = _values()
    for key, value in zip(bias_keys(1), bias, strict=True):
        values.insert(key, value)
    for key in keys:
        values.insert(key, rng.normal(0.0, 0.3, 4))
    _check(f, values)
    # an orthoimage's registration measures east and north only: those rows of the same factor
    horizontal = orbital_factor(0, 1, np.array([5.0, -0.8]), (a @ a.T)[:2, :2] + np.eye(2) * 0.01, keys, (0, 1))
    _check(horizontal, values)
    np.testing.assert_allclose(horizontal.unwhitenedError(values), f.unwhitenedError(values)[:2], atol=1e-12)
    if shared:  # the errors add to the prediction: moving one by d moves the error by d
        moved = gtsam.Values(values)
        moved.update(keys[0], values.atVector(keys[0]) + np.array([0.1, -0.2, 0.05, 0.001]))
        np.testing.assert_allclose(f.unwhitenedError(moved) - f.unwhitenedError(values), [0.1, -0.2, 0.05, 0.001],
                                   atol=1e-12)
