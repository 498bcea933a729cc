"""The stereo_calibration kind: the stereo pair's calibration error estimated through the sites'
stereo views and the VO's steps (kinds/stereo_calibration.py, geometry/calibration_error.py)."""

import pickle
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from pancam_graph.config import SimulationErrors, load_scenario, resolve_scenario, with_vo_error_model
from pancam_graph.geometry.calibration_error import NAMES, pixel_shifts
from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph import tie_gate
from pancam_graph.graph.keys import C, L, X
from pancam_graph.kinds.stereo_calibration import (
    StereoCalibration,
    calibrated_stereo_error,
    calibrated_stereo_factor,
    calibrated_vo_error,
    calibrated_vo_factor,
)
from pancam_graph.sim.errors import TrueRig
from pancam_graph.solve.pipeline import RunOptions, run_scenario

RIG = rig_preset("exomars")
CALIBRATION = RIG.stereo_calibration()
CAMERA = (RIG.wac.fx, RIG.wac.fy, RIG.wac.cx, RIG.wac.cy, RIG.baseline_m)
MOUNT = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.0) .compose(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2)),
                    np.array([0.1, 0.2, 1.5]))
POSE = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, 0.01, -0.02), np.array([5.0, -3.0, 0.2]))
STATE = np.array([2e-4, -1.5e-4, 1e-4, 4e-5, -3e-4, 2e-4])  # rad, rad, rad, ratio, ratio, ratio


def _point_ahead(u: float, v: float, range_m: float) -> np.ndarray:
    """A world point the left camera sees at pixel (u, v), range_m along its axis."""
    ray = np.array([(u - RIG.wac.cx) / RIG.wac.fx, (v - RIG.wac.cy) / RIG.wac.fy, 1.0])
    return POSE.compose(MOUNT).transformFrom(ray * range_m)


def _measured(point: np.ndarray, state: np.ndarray) -> np.ndarray:
    projected = gtsam.StereoCamera(POSE.compose(MOUNT), CALIBRATION).project(point)
    uvv = np.array([projected.uL(), projected.uR(), projected.v()])
    return uvv + pixel_shifts(uvv, RIG.wac.fx, RIG.wac.cx, RIG.wac.cy) @ state


def test_without_a_calibration_error_it_is_gtsams_stereo_factor():
    point = _point_ahead(700.0, 300.0, 12.0) + np.array([0.02, -0.03, 0.01])  # off the measurement
    measured = np.array([650.0, 560.0, 310.0])
    ours = calibrated_stereo_factor(X(0), L(0), measured, CAMERA, MOUNT.matrix(), ("none", None, 0.3, 0.0))
    gtsams = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*measured), gtsam.noiseModel.Isotropic.Sigma(3, 0.3),
                                         X(0), L(0), CALIBRATION, MOUNT)
    values = gtsam.Values()
    values.insert(X(0), POSE)
    values.insert(L(0), point)
    values.insert(C(0), np.zeros(6))
    assert ours.keys() == [X(0), L(0), C(0)]
    np.testing.assert_allclose(ours.unwhitenedError(values), gtsams.unwhitenedError(values), atol=1e-9)
    ours_jacobian, gtsams_jacobian = ours.linearize(values).jacobian()[0], gtsams.linearize(values).jacobian()[0]
    np.testing.assert_allclose(ours_jacobian[:, :9], gtsams_jacobian, atol=1e-7)
    # a checkpoint pickles the factor's plain arguments and makes it again from them
    arguments = pickle.loads(pickle.dumps((X(0), L(0), measured, CAMERA, MOUNT.matrix(), ("none", None, 0.3, 0.0))))
    np.testing.assert_array_equal(calibrated_stereo_factor(*arguments).unwhitenedError(values),
                                  ours.unwhitenedError(values))


def test_the_true_state_explains_the_measurement_and_the_jacobians_match_central_differences():
    point = _point_ahead(300.0, 800.0, 25.0)
    measured = _measured(point, STATE)
    assert np.allclose(calibrated_stereo_error(measured, CALIBRATION, MOUNT, POSE, point, STATE), 0.0, atol=1e-9)
    assert np.all(np.abs(calibrated_stereo_error(measured, CALIBRATION, MOUNT, POSE, point, 0 * STATE)) > 0.05)

    analytic = [None, None, None]
    calibrated_stereo_error(measured, CALIBRATION, MOUNT, POSE, point, STATE, analytic)

    def error(pose=POSE, p=point, state=STATE):
        return calibrated_stereo_error(measured, CALIBRATION, MOUNT, pose, p, state)

    eps = 1e-6
    unit = np.eye(6)
    d_pose = np.column_stack([(error(pose=POSE.retract(eps * unit[i])) - error(pose=POSE.retract(-eps * unit[i])))
                              / (2 * eps) for i in range(6)])
    d_point = np.column_stack([(error(p=point + eps * unit[i, :3]) - error(p=point - eps * unit[i, :3])) / (2 * eps)
                               for i in range(3)])
    unit_c = np.eye(len(NAMES))
    d_state = np.column_stack([(error(state=STATE + 1e-7 * unit_c[i]) - error(state=STATE - 1e-7 * unit_c[i])) / 2e-7
                               for i in range(len(NAMES))])
    np.testing.assert_allclose(analytic[0], d_pose, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(analytic[1], d_point, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(analytic[2], d_state, rtol=1e-6, atol=1e-3)


def test_the_pixel_noise_does_not_pull_the_calibration_one_way():
    """Four sites that see 200 landmarks, nothing but the stereo views between them: the world's
    scale and the baseline's error are one direction that no view observes, held by the
    baseline's prior alone (1e-3 here). With the shifts taken at the measured pixels the
    baseline's term, (u_right - u_left), carried the right pixel's noise that is in the residual
    too, and every view pulled the baseline long: +0.76 sigma on every draw (the common focal
    error +0.52), as the baseline on mars_traverse came out long on nine seeds of ten. At the
    predicted pixels the estimate stays where its prior holds it."""
    rng = np.random.default_rng(1)
    mount = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2), np.zeros(3))  # the camera looks along x
    poses = [gtsam.Pose3(gtsam.Rot3.Yaw(0.05 * i), np.array([3.0 * i, 0.5 * i, 0.0])) for i in range(4)]
    points = np.column_stack([rng.uniform(15, 45, 200), rng.uniform(-8, 8, 200), rng.uniform(-2, 0.5, 200)])
    sigma_px = 0.5
    prior = np.array([np.deg2rad(0.01)] * 3 + [5e-5, 3e-4, 1e-3])
    views = [(i, j, gtsam.StereoCamera(pose.compose(mount), CALIBRATION).project(point))
             for i, pose in enumerate(poses) for j, point in enumerate(points)]
    pulls = []
    for _ in range(5):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose3(X(0), poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        graph.add(gtsam.PriorFactorVector(C(0), np.zeros(6), gtsam.noiseModel.Diagonal.Sigmas(prior)))
        for i, pose in enumerate(poses):
            values.insert(X(i), pose)
        for j, point in enumerate(points):
            values.insert(L(j), point + rng.normal(0.0, 0.05, 3))
        values.insert(C(0), np.zeros(6))
        for i, j, true in views:
            measured = np.array([true.uL(), true.uR(), true.v()]) + rng.normal(0.0, sigma_px, 3)
            graph.add(calibrated_stereo_factor(X(i), L(j), measured, CAMERA, mount.matrix(),
                                               ("none", None, sigma_px, 0.0)))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        sigmas = np.sqrt(np.diag(gtsam.Marginals(graph, result).marginalCovariance(C(0))))
        pulls.append(result.atVector(C(0)) / sigmas)
    mean_pull = np.mean(pulls, axis=0)
    assert abs(mean_pull[NAMES.index("baseline_scale")]) < 0.1  # measured 0.00 (+0.76 at the measured pixels)
    assert abs(mean_pull[NAMES.index("focal_scale")]) < 0.1  # measured -0.004 (+0.52)


def test_its_first_order_model_is_the_simulators_miscalibrated_pair_across_the_image():
    """The kind's correction against sim/errors.py's exact geometry of a miscalibrated pair (this
    draw: both focal lengths 0.063 % long, the right one 0.014 % more, the right camera turned
    0.002-0.02 deg, the baseline 0.26 % short): the same pixels within 0.002 px over the whole
    image at 2-40 m, where the error itself reaches 1.0 px."""
    errors = SimulationErrors(focal_scale_sigma=6e-4, focal_difference_sigma=8e-5, boresight_sigma_deg=0.015,
                              baseline_scale_sigma=1e-3)
    true_rig = TrueRig.draw(RIG, errors, np.random.default_rng(6))
    state = np.array([true_rig.state(RIG)[name] for name in NAMES])
    u, v = (grid.ravel() for grid in np.meshgrid(np.linspace(20, 1004, 9), np.linspace(20, 1004, 9)))
    worst, largest = 0.0, 0.0
    for range_m in (2.0, 8.0, 40.0):
        points = np.column_stack([(u - RIG.wac.cx) / RIG.wac.fx, (v - RIG.wac.cy) / RIG.wac.fy, np.ones(u.size)])
        points *= range_m
        nominal = np.column_stack([u, RIG.wac.fx * (points[:, 0] - RIG.baseline_m) / points[:, 2] + RIG.wac.cx, v])
        true_uv, true_u_right = true_rig.observe(points)
        true = np.column_stack([true_uv[:, 0], true_u_right, true_uv[:, 1]])
        for k in range(len(points)):
            predicted = nominal[k] + pixel_shifts(true[k], RIG.wac.fx, RIG.wac.cx, RIG.wac.cy) @ state
            worst = max(worst, float(np.abs(predicted - true[k]).max()))
            largest = max(largest, float(np.abs(true[k] - nominal[k]).max()))
    assert largest > 1.0  # measured 1.02 px (1.49 without the baseline's error)
    assert worst < 0.005  # measured 0.0016 px


def test_its_correction_triangulates_a_miscalibrated_pairs_points_where_they_are():
    """What triangulates a site outside the graph (the orbital kind's elevation map, the sites'
    anchors and first guesses) takes the pixels through Kind.site_stereo_pixels. This draw turns
    the right camera by 0.02 deg about its vertical and shortens the baseline by 0.26 %: through
    the nominal pair, points 10-40 m away land up to 1.29 m off; corrected with the error known,
    within 3.3 mm (the correction's first order)."""
    errors = SimulationErrors(boresight_sigma_deg=0.02, baseline_scale_sigma=1e-3, focal_scale_sigma=6e-4)
    true_rig = TrueRig.draw(RIG, errors, np.random.default_rng(6))
    error = np.array([true_rig.state(RIG)[name] for name in NAMES])
    kind = StereoCalibration.__new__(StereoCalibration)
    kind.loc = SimpleNamespace(traverse=SimpleNamespace(rig=RIG), smoother=SimpleNamespace(vector=lambda key: error))
    rng = np.random.default_rng(2)
    ranges = rng.uniform(10.0, 40.0, 50)
    truth = np.column_stack([rng.uniform(-0.3, 0.3, 50) * ranges, rng.uniform(-0.3, 0.3, 50) * ranges, ranges])
    uv, u_right = true_rig.observe(truth)
    views = {track: [(gtsam.Pose3(), np.array([uv[track, 0], u_right[track], uv[track, 1]]))] for track in range(50)}
    off = {}
    for label, corrected in (("nominal", None), ("corrected", kind.site_stereo_pixels)):
        seen = tie_gate.site_points(views if corrected is None else tie_gate.corrected_views(views, corrected),
                                    RIG, 0.3)
        off[label] = max(np.linalg.norm(seen[track].p_body - truth[track]) for track in range(50))
    assert off["nominal"] > 1.0  # measured 1.29 m
    assert off["corrected"] < 0.01  # measured 0.0033 m


def test_a_realistic_profile_estimates_the_calibration_unless_the_estimator_says_otherwise():
    text = resolve_scenario("short_trail").read_text()  # realistic, as bundled
    realistic = load_scenario_text(text)
    assert realistic.estimator.calibration == "estimated"
    assert realistic.estimator.configurations["vo_sites"] == ["vo", "sites", "stereo_calibration"]
    assert realistic.estimator.configurations["vo"] == ["vo", "stereo_calibration"]
    assert "stereo_calibration" not in realistic.estimator.configurations["dead_reckoning"]
    trusted = load_scenario_text(text + '\n[estimator]\ncalibration = "trusted"\n')
    assert trusted.estimator.configurations["vo_sites"] == ["vo", "sites"]
    ideal = load_scenario(resolve_scenario("short_trail"), errors="ideal")
    assert ideal.estimator.calibration == "auto" and ideal.estimator.configurations["vo_sites"] == ["vo", "sites"]


def test_the_real_image_vo_model_leaves_the_estimated_calibration_its_vo_steps():
    """The real_images VO model adds vo_scale to every configuration with VO; under an estimated
    calibration stereo_calibration builds the VO steps' factors instead, and the two together were
    refused ("both build the vo steps' factors"), in a scenario and from `--vo-error-model`."""
    text = resolve_scenario("short_trail").read_text()  # realistic, as bundled
    in_file = load_scenario_text(text + '\n[estimator]\nvo_error_model = "real_images"\n').estimator
    from_cli = with_vo_error_model(load_scenario_text(text).estimator, "real_images")
    for estimator in (in_file, from_cli):
        assert estimator.vo_error_model == "real_images"
        assert estimator.configurations["vo"] == ["vo", "stereo_calibration"]
        assert estimator.configurations["vo_sites"] == ["vo", "sites", "stereo_calibration"]
    # without the calibration estimated, the model still adds its shared scale
    trusted = load_scenario_text(text + '\n[estimator]\ncalibration = "trusted"\nvo_error_model = "real_images"\n')
    assert trusted.estimator.configurations["vo"] == ["vo", "vo_scale"]


def load_scenario_text(text: str):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scenario.toml"
        path.write_text(text)
        return load_scenario(path)


@pytest.mark.parametrize("seed", [2, 3])
def test_estimated_the_realistic_calibration_leaves_the_sites_consistent_and_nearer_the_truth(seed):
    """short_trail under the realistic profile: trusting the calibration, vo_sites is over-confident
    (ANEES 11 and 69 on these seeds, measured; 75 and 135 before the tracking errors, whose
    VO steps claim more); estimating it brings the ANEES under 2, the
    unaligned ATE down, and the right camera's turn about the vertical within 3 sigma of the
    simulator's."""
    scenario = load_scenario(resolve_scenario("short_trail"))  # realistic, as bundled
    trusted_estimator = scenario.estimator.model_copy(update={"configurations": {"vo_sites": ["vo", "sites"]}})
    estimated = run_scenario(scenario, RunOptions(seed=seed, configs=["vo_sites"])).configurations["vo_sites"]
    trusted = run_scenario(scenario.model_copy(update={"estimator": trusted_estimator}),
                           RunOptions(seed=seed, configs=["vo_sites"])).configurations["vo_sites"]
    assert trusted.consistency.anees > 5.0
    assert estimated.consistency.anees < 2.0
    assert estimated.metrics.ate_unaligned_rmse_m < 0.6 * trusted.metrics.ate_unaligned_rmse_m
    turn = estimated.counters
    assert abs(turn["right_rotation_y_rad_error"]) < 3.0 * turn["right_rotation_y_rad_sigma"]
    assert turn["right_rotation_y_rad_sigma"] < 0.3 * np.deg2rad(0.01)  # the sites observe it, not the prior


def test_a_vo_step_measured_through_a_miscalibrated_pair_comes_back_with_its_calibration_error():
    """Two stops 1.5 m apart, noiseless pixels through the simulator's miscalibrated pair (turned
    0.02 deg about the vertical among the rest): the two-stop adjustment's step is off the truth
    by a pitch of 116 urad and 0.5 mm (measured); the step corrected by its sensitivity and the
    true error by 0.06 urad and 0.0001 mm. The factor's Jacobians are central differences'."""
    from pancam_graph.frontend.two_stop_adjustment import StereoIntrinsics, adjust_two_stops
    from pancam_graph.geometry.rig import triangulate_rectified

    rng = np.random.default_rng(4)
    errors = SimulationErrors(focal_scale_sigma=3e-4, focal_difference_sigma=5e-5, boresight_sigma_deg=0.02,
                              baseline_scale_sigma=1e-4)
    true_rig = TrueRig.draw(RIG, errors, np.random.default_rng(11))
    state = np.array([true_rig.state(RIG)[name] for name in NAMES])
    body_T_left = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2 - np.deg2rad(20.0)), [0.0, 0.1, 1.9])
    truth = gtsam.Pose3(gtsam.Rot3.Ypr(np.deg2rad(3.0), 0.002, -0.001), [1.5, 0.05, 0.01])
    cam = np.column_stack([rng.uniform(-4, 4, 150), rng.uniform(0.5, 1.8, 150), rng.uniform(3, 30, 150)])
    cam1 = np.array([(body_T_left.inverse() * truth.inverse() * body_T_left).transformFrom(p) for p in cam])

    def observed(points):
        uv, u_right = true_rig.observe(points)
        return np.column_stack([uv[:, 0], u_right, uv[:, 1]])

    a, b = observed(cam), observed(cam1)
    start = triangulate_rectified(a[:, 0], a[:, 1], a[:, 2], RIG.wac, RIG.baseline_m)
    solution = adjust_two_stops(a, b, start, truth, StereoIntrinsics.of(CALIBRATION), body_T_left, 0.3)
    vo_T, sensitivity = solution.prev_T_curr, solution.calibration_sensitivity
    off = truth.localCoordinates(vo_T)
    corrected = truth.localCoordinates(vo_T.compose(gtsam.Pose3.Expmap(sensitivity @ state)))
    assert np.linalg.norm(off[:3]) > 5e-5  # the miscalibrated pair turns the step
    assert np.linalg.norm(corrected[:3]) < 0.01 * np.linalg.norm(off[:3])
    assert np.linalg.norm(corrected[3:]) < 0.01 * np.linalg.norm(off[3:])

    # the factor: zero at the truth with the true error, and its Jacobians
    world_T_a = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, 0.02, -0.01), np.array([10.0, 4.0, -1.0]))
    world_T_b = world_T_a.compose(truth)
    assert np.abs(calibrated_vo_error(vo_T, sensitivity, world_T_a, world_T_b, state)).max() < \
        0.05 * np.abs(calibrated_vo_error(vo_T, sensitivity, world_T_a, world_T_b, 0 * state)).max()
    analytic = [None, None, None]
    c = state * 3.0
    calibrated_vo_error(vo_T, sensitivity, world_T_a, world_T_b, c, analytic)
    unit, eps = np.eye(6), 1e-6

    def error(a=world_T_a, b=world_T_b, cal=c):
        return calibrated_vo_error(vo_T, sensitivity, a, b, cal)

    d_a = np.column_stack([(error(a=world_T_a.retract(eps * u)) - error(a=world_T_a.retract(-eps * u))) / (2 * eps)
                           for u in unit])
    d_b = np.column_stack([(error(b=world_T_b.retract(eps * u)) - error(b=world_T_b.retract(-eps * u))) / (2 * eps)
                           for u in unit])
    d_c = np.column_stack([(error(cal=c + 1e-7 * u) - error(cal=c - 1e-7 * u)) / 2e-7 for u in unit])
    np.testing.assert_allclose(analytic[0], d_a, atol=1e-6)
    np.testing.assert_allclose(analytic[1], d_b, atol=1e-6)
    np.testing.assert_allclose(analytic[2], d_c, rtol=1e-5, atol=1e-6)
    # a checkpoint makes the factor again from its plain arguments
    arguments = (X(0), X(1), vo_T, np.eye(6) * 1e-4, sensitivity)
    values = gtsam.Values()
    values.insert(X(0), world_T_a)
    values.insert(X(1), world_T_b)
    values.insert(C(0), c)
    np.testing.assert_array_equal(calibrated_vo_factor(*pickle.loads(pickle.dumps(arguments))).unwhitenedError(values),
                                  calibrated_vo_factor(*arguments).unwhitenedError(values))
