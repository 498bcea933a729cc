"""The onboard kind (kinds/onboard.py): a rover's onboard increments as its motion, with the
error model of its settings, and its onboard tilt at each stop as an attitude factor."""

import dataclasses

import gtsam
import numpy as np
import pytest

from pancam_graph.config import EstimatorConfig
from pancam_graph.frontend.motion import dead_reckoning_motion
from pancam_graph.geometry.geodesy import LocalFrame
from pancam_graph.geometry.rig import BODY_T_FORWARD_CAMERA, Camera, Rig
from pancam_graph.kinds import unavailable
from pancam_graph.kinds.base import RowError
from pancam_graph.kinds.onboard import Onboard, OnboardSettings, OnboardTilt, step_covariance
from pancam_graph.records import DeadReckoning, SlipPrior, StereoObservations, Stop, Traverse
from pancam_graph.solve.localizer import Localizer


def _pose(yaw: float, pitch: float, xyz) -> np.ndarray:
    return gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, 0.0), np.asarray(xyz, float)).matrix()


TRUE = [_pose(0.1 * k, 0.02 * np.sin(k), [5.0 * k, 0.5 * k * k, 0.1 * k]) for k in range(8)]


def _traverse(odometry_pitch_error: float = 0.0, tilts: bool = True) -> Traverse:
    stops = []
    for k, pose in enumerate(TRUE):
        step = None
        if k:
            increment = np.linalg.inv(TRUE[k - 1]) @ pose
            # the onboard attitude propagation drifts in pitch step by step
            increment = increment @ _pose(0.0, odometry_pitch_error, [0, 0, 0])
            step = DeadReckoning(increment, step_covariance(increment, OnboardSettings()))
        stops.append(Stop(k, 10.0 * k, StereoObservations.empty(), dead_reckoning=step))
    origin = LocalFrame(-4.59, 137.44, 0.0, body="mars")
    # gravity where the rover stands: the vertical turns by distance / radius from the origin's
    ups = origin.up_at(np.array(TRUE)[:, :3, 3])
    records = tuple(OnboardTilt(k, pose[:3, :3].T @ up) for k, (pose, up) in enumerate(zip(TRUE, ups, strict=True)))
    rig = Rig("test", Camera(500.0, 500.0, 320.0, 240.0, 640, 480), 0.4, 1.9)
    return Traverse("onboard test", rig, origin, tuple(stops), 0.0, 0.5,
                    np.zeros(3), TRUE[0], np.array([1e-4] * 3 + [1e-3] * 3), SlipPrior(0.0, 1e-6),
                    BODY_T_FORWARD_CAMERA, {"onboard": records} if tilts else {})


def _solve(traverse: Traverse, settings: OnboardSettings = OnboardSettings()) -> np.ndarray:
    estimator = EstimatorConfig(configurations={"onboard": ["onboard"]}, onboard=settings)
    loc = Localizer(traverse, ["onboard"], estimator)
    motion = None
    for stop in traverse.stops:
        motion = None if stop.index == 0 else dead_reckoning_motion(stop, motion, traverse.wheel_slip)
        loc.step(stop, motion)
    return np.array([loc.pose(k) for k in range(len(traverse.stops))])


def test_exact_increments_give_back_the_onboard_chain():
    poses = _solve(_traverse())
    np.testing.assert_allclose(poses[:, :3, 3], np.array(TRUE)[:, :3, 3], atol=1e-6)


def test_the_onboard_tilt_takes_out_a_pitch_drift_the_increments_carry():
    drift = np.deg2rad(0.5)  # a step's pitch error, 2.5 times the step's stated rotation sigma
    def pitch_error(poses):
        return max(abs(gtsam.Rot3(p[:3, :3]).between(gtsam.Rot3(t[:3, :3])).pitch())
                   for p, t in zip(poses, TRUE, strict=True))
    with_tilt = pitch_error(_solve(_traverse(drift)))
    without = _solve(_traverse(drift, tilts=False), OnboardSettings(tilt_sigma_deg=30.0))
    assert np.rad2deg(pitch_error(without)) > 2.0  # 7 steps of 0.5 deg, barely held by a 30 deg tilt
    assert np.rad2deg(with_tilt) < 0.5


def test_the_step_covariance_is_the_stated_percent_of_the_step_with_a_floor():
    settings = OnboardSettings(distance_percent=3.0, floor_m=0.02, rotation_sigma_deg=0.2)
    step = _pose(0.0, 0.0, [30.0, 40.0, 0.0])  # 50 m
    sigmas = np.sqrt(np.diag(step_covariance(step, settings)))
    np.testing.assert_allclose(sigmas[3:], 1.5)
    np.testing.assert_allclose(sigmas[:3], np.deg2rad(0.2))
    np.testing.assert_allclose(np.sqrt(np.diag(step_covariance(np.eye(4), settings)))[3:], 0.02)


def test_a_traverse_without_onboard_telemetry_cannot_feed_it():
    traverse = _traverse(tilts=False)
    assert "onboard rover telemetry" in unavailable(["onboard"], traverse)
    no_steps = dataclasses.replace(_traverse(), stops=tuple(dataclasses.replace(s, dead_reckoning=None)
                                                            for s in _traverse().stops))
    assert unavailable(["onboard"], no_steps) is not None


@pytest.mark.parametrize("row, words", [((0, 0.0, 0.0, 2.0), "not a unit vector"),
                                        ((99, 0.0, 0.0, 1.0), "expected a stop index"),
                                        ((0.5, 0.0, 0.0, 1.0), "expected a stop index")])
def test_a_bad_tilt_row_is_refused_naming_its_line(row, words):
    with pytest.raises(RowError, match=words) as caught:
        Onboard.from_rows([(7, row)], _traverse())
    assert caught.value.line == 7


def test_its_rows_read_back():
    records = _traverse().measurements["onboard"]
    back = Onboard.from_rows(list(enumerate(Onboard.to_rows(records), start=2)), _traverse())
    assert [r.stop for r in back] == [r.stop for r in records]
    np.testing.assert_allclose([r.up_body for r in back], [r.up_body for r in records])
