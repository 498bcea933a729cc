"""GPS used at its own time: a fix taken while driving constrains a pose inserted at its time."""

import numpy as np
import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.records import GpsFix
from pancam_graph.sim import simulate
from pancam_graph.solve.localizer import Localizer
from pancam_graph.solve.pipeline import run_scenario
from pancam_graph.solve.results import RunOptions


def _with(scenario, **gps):
    estimator = scenario.estimator
    return scenario.model_copy(update={"estimator": estimator.model_copy(
        update={"gps": estimator.gps.model_copy(update=gps)})})


@pytest.fixture(scope="module")
def driving():
    return load_scenario(resolve_scenario("gps_driving"))


@pytest.mark.slow
def test_fixes_between_stops_beat_attaching_them_to_the_nearest_stop(driving):
    """gps_driving: 1 Hz differential GPS (0.5 m) while driving between stops 2-10 m apart. Ignoring
    the fix times (the nearest stop takes each fix) costs twice the error."""
    timed = run_scenario(driving, RunOptions(seed=0, configs=("full",))).configurations["full"]
    nearest = run_scenario(_with(driving, time_association="nearest_stop"),
                  RunOptions(seed=0, configs=("full",))).configurations["full"]
    assert len(timed.interpolated) > 1000 and len(nearest.interpolated) == 0
    assert timed.counter("gps_fixes_used") == nearest.counter("gps_fixes_used") > 1500
    assert timed.metrics.ate_rmse_m <= 0.7 * nearest.metrics.ate_rmse_m
    assert timed.metrics.ate_rmse_m < 0.5  # below the GPS sigma


@pytest.mark.slow
def test_splitting_the_motion_keeps_its_information(short_scenario):
    """Fixes with a useless sigma: the poses inserted at their times and the split motion factors
    must leave the stops' covariances as they are without them."""
    gps = short_scenario.gps.model_copy(update={"rate_hz": 0.5, "sigma_horizontal_m": 1e5, "sigma_vertical_m": 1e5})
    scenario = short_scenario.model_copy(update={"gps": gps})
    result = run_scenario(scenario, RunOptions(seed=1, configs=("vo", "vo+gps")))
    plain, split = result.configurations["vo"], result.configurations["vo+gps"]
    assert len(split.interpolated) > 100
    np.testing.assert_allclose(split.world_T_body[:, :3, 3], plain.world_T_body[:, :3, 3], atol=2e-3)
    sigma = lambda c: np.sqrt(np.trace(c.position_covariance, axis1=1, axis2=2))  # noqa: E731
    np.testing.assert_allclose(sigma(split), sigma(plain), rtol=0.02)


def test_fixes_outside_the_drive_are_refused_with_a_reason(short_scenario):
    traverse, _ = simulate(short_scenario, 0)
    first, last = traverse.stops[0], traverse.stops[-1]
    fix = traverse.gps_fixes[0]
    early = GpsFix(first.time_s - 10.0, fix.lat_deg, fix.lon_deg, fix.h_m, 2.0, 3.0)
    late = GpsFix(last.departure_s + 10.0, fix.lat_deg, fix.lon_deg, fix.h_m, 2.0, 3.0)
    from dataclasses import replace

    a, b = traverse.stops[3], traverse.stops[4]
    mid = GpsFix(0.5 * (a.departure_s + b.time_s), fix.lat_deg, fix.lon_deg, fix.h_m, 2.0, 3.0)
    fixes = sorted((early, mid, *traverse.gps_fixes, late), key=lambda f: f.time_s)
    traverse = replace(traverse, measurements={**traverse.measurements, "gps": tuple(fixes)})
    long_drive = _with(short_scenario, max_gap_s=1.0).estimator
    loc = Localizer(traverse, ["dead_reckoning", "gps"], long_drive)
    gps = loc.kinds["gps"]
    assert gps.refused_count == 1 and "before the first stop" in gps.refused[0]
    from pancam_graph.frontend.motion import dead_reckoning_motion

    motion = None
    for stop in traverse.stops:
        motion = None if stop.index == 0 else dead_reckoning_motion(stop, motion, traverse.wheel_slip)
        loc.step(stop, motion)
    loc.finish()
    assert "after the last stop's departure" in gps.refused[-1]
    assert gps.refused_count == 3 and "longer than [estimator.gps] max_gap_s = 1 s" in gps.refused[1]
    assert not loc.interpolated  # the refused fix got no pose
