"""The simulator's error profiles ([errors], sim/errors.py): the ideal profile is the simulator
as it was; a stereo calibration error shows as the disparity error the pair's geometry predicts;
the mast's readings are the true angles rounded; ties between sites are as many as the image
matcher finds at that distance, each off by its matching error, and the rest new landmarks; the
navigation features err as the image front-end's do, and the VO claims what that does to it."""

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from pancam_graph.config import Scenario, SimulationErrors, load_scenario, resolve_scenario
from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph.tie_matching import count as tie_count
from pancam_graph.records import PanoramaFrame, StereoObservations, Stop
from pancam_graph.sim import simulate
from pancam_graph.sim.errors import TrackingErrors, TrueRig, match_ties, with_pointing_error


@pytest.fixture(scope="module")
def short_trail():
    return load_scenario(resolve_scenario("short_trail"), errors="ideal")


def _with_errors(scenario, **errors) -> Scenario:
    return Scenario.model_validate({**scenario.model_dump(), "errors": errors})


def _short_trail(errors: dict | None, **estimator) -> Scenario:
    """short_trail with `errors` as its [errors] table (None: none at all) and `estimator`'s
    [estimator.<section>] tables, validated as a file saying so would be."""
    data = tomllib.loads(resolve_scenario("short_trail").read_text())
    data.pop("errors", None)
    if errors is not None:
        data["errors"] = errors
    data["estimator"] = {**data.get("estimator", {}), **estimator}
    return Scenario.model_validate(data)


def test_the_bundled_scenarios_are_realistic_unless_told_otherwise():
    from pancam_graph.config import bundled_scenarios

    for name, path in bundled_scenarios().items():
        assert load_scenario(path).errors.profile == "realistic", name
        assert load_scenario(path, errors="ideal").errors == SimulationErrors(), name


def test_the_ideal_profile_is_the_simulator_as_it_was():
    """An explicit ideal profile draws nothing more than a scenario without an [errors] table:
    the same traverse to the bit."""
    a, truth_a = simulate(_short_trail(None), 3)
    b, truth_b = simulate(_short_trail({"profile": "ideal"}), 3)
    for x, y in zip(a.stops, b.stops, strict=True):
        np.testing.assert_array_equal(x.stereo.uvv, y.stereo.uvv)
        for fx, fy in zip(x.panorama, y.panorama, strict=True):
            np.testing.assert_array_equal(fx.observations.uvv, fy.observations.uvv)
    np.testing.assert_array_equal(truth_a.landmarks, truth_b.landmarks)


def test_the_realistic_profile_takes_every_magnitude_from_its_table_unless_given():
    errors = SimulationErrors.model_validate({"profile": "realistic", "boresight_sigma_deg": 0.05})
    assert errors.boresight_sigma_deg == 0.05 and errors.focal_scale_sigma == 0.0003
    assert errors.tie_matching == "measured" and errors.pan_tilt_resolution_deg == 0.013
    assert errors.stereo_tracking == "measured"


def test_a_right_camera_turned_about_the_vertical_biases_every_disparity_by_f_times_the_angle():
    """Against the small-angle formula: a yaw delta of the right camera shifts u_right by
    -f delta (1 + x^2/z^2) nearly (x/z the ray's tangent in the right camera): 0.30 px at
    any range for 0.01 deg; a baseline error scales the disparity."""
    rig = rig_preset("exomars")
    delta = np.deg2rad(0.01)
    rotation = np.array([[np.cos(delta), 0.0, np.sin(delta)], [0.0, 1.0, 0.0], [-np.sin(delta), 0.0, np.cos(delta)]])
    exact = TrueRig(rig.wac, rig.wac, rig.baseline_m, np.eye(3))
    turned = replace(exact, left_R_right=rotation)
    longer = replace(exact, baseline_m=rig.baseline_m * 1.01)
    p = np.column_stack([np.zeros(4), np.zeros(4), [3.0, 10.0, 30.0, 100.0]])
    uv, u_right = exact.observe(p)
    np.testing.assert_allclose(uv[:, 0] - u_right, rig.wac.fx * rig.baseline_m / p[:, 2], rtol=1e-12)
    _, u_turned = turned.observe(p)
    x_right = (p[:, 0] - rig.baseline_m) / p[:, 2]  # the ray's tangent in the right camera
    np.testing.assert_allclose(u_turned - u_right, -rig.wac.fx * delta * (1 + x_right**2), rtol=1e-3)  # 0.30 px
    _, u_longer = longer.observe(p)
    np.testing.assert_allclose((uv[:, 0] - u_longer) / (uv[:, 0] - u_right), 1.01, rtol=1e-12)


def test_a_drawn_pair_is_the_pair_its_state_says():
    """TrueRig.of_state inverts TrueRig.state: the pair a render or a check rebuilds from the
    truth's stereo_calibration projects as the drawn one does."""
    rig = rig_preset("exomars")
    errors = SimulationErrors.model_validate({"profile": "realistic", "boresight_sigma_deg": 0.2})
    drawn = TrueRig.draw(rig, errors, np.random.default_rng(4))
    rebuilt = TrueRig.of_state(rig, drawn.state(rig))
    p = np.column_stack([np.linspace(-3.0, 3.0, 5), np.linspace(-1.0, 1.5, 5), [3.0, 8.0, 15.0, 30.0, 60.0]])
    (uv, u_right), (uv_rebuilt, u_right_rebuilt) = drawn.observe(p), rebuilt.observe(p)
    # a draw worth rebuilding: pixels off the calibrated pair's by more than a pixel
    assert np.abs(u_right - (uv[:, 0] - rig.wac.fx * rig.baseline_m / p[:, 2])).max() > 1.0
    np.testing.assert_allclose(uv_rebuilt, uv, atol=1e-9)
    np.testing.assert_allclose(u_right_rebuilt, u_right, atol=1e-9)
    # and the point a true left pixel sees at a depth is the point that projects there
    np.testing.assert_allclose(drawn.left_point(uv[:, 0], uv[:, 1], p[:, 2]), p, atol=1e-9)


def test_mast_readings_are_the_true_angles_within_half_the_resolution():
    errors = SimulationErrors(pan_tilt_resolution_deg=0.5)
    rng = np.random.default_rng(0)
    true = np.array([with_pointing_error(0.3, -0.1, errors, rng) for _ in range(4000)])
    offsets = np.rad2deg(true - [0.3, -0.1])
    assert np.all(np.abs(offsets) <= 0.25) and np.all(np.abs(offsets).max(axis=0) > 0.24)
    np.testing.assert_allclose(offsets.std(axis=0), 0.5 / np.sqrt(12), rtol=0.05)  # uniform


def test_ties_are_as_many_as_the_matcher_finds_and_the_rest_are_new_landmarks(short_trail):
    ideal, truth_ideal = simulate(short_trail, 0)
    measured, truth = simulate(_with_errors(short_trail, tie_matching="measured"), 0)
    sites = [s.index for s in ideal.stops if s.site_id is not None]
    assert len(sites) >= 3
    n = len(truth_ideal.landmarks)
    fresh = np.arange(n, len(truth.landmarks))
    assert len(fresh) > 0
    positions = truth.world_T_body[:, :3, 3]

    def ids(traverse, k):
        stop = traverse.stops[k]
        return set(np.concatenate([f.observations.track_ids for f in stop.panorama]).tolist())

    expected, found = [], []
    for a, b in zip(sites, sites[1:], strict=False):
        shared_before = ids(ideal, a) & ids(ideal, b)
        kept = ids(measured, a) & ids(measured, b)
        assert kept <= shared_before
        assert len(shared_before) > 5 * len(kept)  # the identity model ties far more
        expected.append(tie_count(float(np.linalg.norm(positions[b] - positions[a]))))
        found.append(len(kept))
    # Poisson draws around the measured count (a kept id may be another pair's tie too)
    assert abs(np.sum(found) - np.sum(expected)) < 4 * np.sqrt(np.sum(expected)) + 0.1 * np.sum(expected)
    # every new landmark is where the landmark it replaces is: the truth stays true
    for stop_ideal, stop in zip(ideal.stops, measured.stops, strict=True):
        for f_ideal, f in zip(stop_ideal.panorama, stop.panorama, strict=True):
            renamed = f.observations.track_ids >= n
            np.testing.assert_array_equal(truth.landmarks[f.observations.track_ids],
                                          truth_ideal.landmarks[f_ideal.observations.track_ids])
            np.testing.assert_array_equal(f.observations.uvv[renamed], f_ideal.observations.uvv[renamed])
    # a kept tie's views at the later site are off by one matching error, the same in each view
    b = sites[1]
    kept = sorted(ids(measured, sites[0]) & ids(measured, b))
    shifts = []
    for f_ideal, f in zip(ideal.stops[b].panorama, measured.stops[b].panorama, strict=True):
        at = np.isin(f.observations.track_ids, kept)
        d = f.observations.uvv[at] - f_ideal.observations.uvv[at]
        np.testing.assert_allclose(d[:, 0], d[:, 1])  # both eyes: the same ground point's disparity
        shifts += [(i, *row) for i, row in zip(f.observations.track_ids[at], d[:, [0, 2]], strict=True)]
    by_tie = {}
    for i, du, dv in shifts:
        by_tie.setdefault(i, []).append((du, dv))
    assert all(np.ptp(np.array(v), axis=0).max() < 1e-9 for v in by_tie.values())
    median = np.median([np.hypot(*v[0]) for v in by_tie.values()])
    assert 0.1 < median < 1.5  # the measured matching error: a median of 0.45 px


def _site(index: int, ids: np.ndarray) -> Stop:
    observations = StereoObservations(ids.astype(np.int64), np.tile([500.0, 480.0, 400.0], (len(ids), 1)))
    return Stop(index, float(index), observations, site_id=index, panorama=(PanoramaFrame(0.0, 0.0, observations),))


@pytest.mark.parametrize("memory", [1, 2])
def test_a_site_ties_only_to_the_sites_it_remembers_and_renames_what_older_ones_saw(memory):
    # A sees 0-199, B 200-399, C 0-99 and 200-299, 10 m apart: C may tie what B saw, and what
    # A saw only when it remembers two sites; otherwise those are new landmarks (fresh ids).
    stops = [_site(0, np.arange(200)), _site(1, np.arange(200, 400)),
             _site(2, np.r_[np.arange(100), np.arange(200, 300)])]
    positions = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    out, fresh = match_ties(stops, positions, 400, memory, 1.0, np.random.default_rng(5))
    c = out[2].panorama[0].observations.track_ids
    seen_by_a, seen_by_b = c[:100], c[100:]
    assert (seen_by_b < 400).sum() > 50  # about 130 drawn, all 100 shared kept
    renamed = seen_by_a[seen_by_a >= 400]
    assert sorted(np.asarray(fresh)[renamed - 400]) == sorted(set(range(100)) - set(seen_by_a.tolist()))
    if memory == 1:
        assert len(renamed) == 100
    else:
        assert (seen_by_a < 400).sum() > 50
    np.testing.assert_array_equal(out[0].panorama[0].observations.track_ids, np.arange(200))  # nothing before A


def test_an_error_changes_what_it_should_and_leaves_every_other_draw_in_place(short_trail):
    """Each error on its own: the same landmarks seen at every stop, the same odometry, and
    pixels moved only where the error acts (the mast's angles: the panorama frames only)."""
    ideal, _ = simulate(short_trail, 1)
    for errors, navigation_moves in (({"pan_tilt_resolution_deg": 0.05}, False),
                                     ({"boresight_sigma_deg": 0.01}, True)):
        traverse, _ = simulate(_with_errors(short_trail, **errors), 1)
        moved = []
        for a, b in zip(ideal.stops, traverse.stops, strict=True):
            np.testing.assert_array_equal(a.stereo.track_ids, b.stereo.track_ids)
            if a.dead_reckoning is not None:
                np.testing.assert_array_equal(a.dead_reckoning.prev_T_curr, b.dead_reckoning.prev_T_curr)
            if len(a.stereo.uvv):
                moved.append(np.abs(a.stereo.uvv - b.stereo.uvv).max())
            for fa, fb in zip(a.panorama, b.panorama, strict=True):
                np.testing.assert_array_equal(fa.observations.track_ids, fb.observations.track_ids)
                if len(fa.observations.uvv):
                    assert np.abs(fa.observations.uvv - fb.observations.uvv).max() > 0.0
        assert (max(moved) > 0.01) == navigation_moves, errors


def test_the_estimator_weights_ties_by_the_matchers_error_where_the_simulator_draws_it():
    realistic = {"profile": "realistic"}
    sites = {label: scenario.estimator.sites.tie_error for label, scenario in (
        ("ideal", _short_trail(None)),
        ("realistic", _short_trail(realistic)),
        ("measured ties", _short_trail({"tie_matching": "measured"})),
        ("realistic, identity ties", _short_trail({**realistic, "tie_matching": "identity"})),
        ("said otherwise", _short_trail(realistic, sites={"tie_error": "pixel_noise"})),
    )}
    assert sites == {"ideal": None, "realistic": "measured", "measured ties": "measured",
                     "realistic, identity ties": None, "said otherwise": "pixel_noise"}


def test_the_estimator_weights_an_hrc_view_with_the_masts_pointing_error_where_the_simulator_draws_it():
    realistic = {"profile": "realistic"}
    pointing = {label: scenario.estimator.hrc.pointing_sigma_deg for label, scenario in (
        ("ideal", _short_trail(None)),
        ("realistic", _short_trail(realistic)),
        ("coarser mast", _short_trail({"pan_tilt_resolution_deg": 0.1})),
        ("said otherwise", _short_trail(realistic, hrc={"pointing_sigma_deg": 0.0})),
    )}
    assert pointing["ideal"] is None and pointing["said otherwise"] == 0.0
    # a reading within half the resolution, uniform: resolution / sqrt(12)
    assert pointing["realistic"] == pytest.approx(0.013 / np.sqrt(12), rel=1e-12)
    assert pointing["coarser mast"] == pytest.approx(0.1 / np.sqrt(12), rel=1e-12)


def _vo_sites_run(tmp_path, name: str, source: str, *options: str) -> dict:
    from typer.testing import CliRunner

    from pancam_graph.cli import app

    out = tmp_path / name
    result = CliRunner().invoke(app, ["run", source, "--seed", "0", "--configs", "vo_sites", "--out", str(out),
                                      "--quiet", "--no-plots", *options])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())["configs"]["vo_sites"]
    metrics.pop("isam2_update_ms")
    return metrics


def test_run_errors_sets_the_profile_in_place_of_the_scenarios_table(tmp_path):
    """`run --errors PROFILE` gives the run a scenario with that profile's table gives, the
    estimator's defaults included (the realistic profile estimates the calibration): an ideal
    file run realistic is the bundled (realistic) run, the bundled run ideal the ideal file's."""
    ideal_file = tmp_path / "ideal.toml"
    ideal_file.write_text(resolve_scenario("short_trail").read_text().replace('profile = "realistic"',
                                                                              'profile = "ideal"'))
    bundled = _vo_sites_run(tmp_path, "bundled", "short_trail")
    flag = _vo_sites_run(tmp_path, "flag", str(ideal_file), "--errors", "realistic")
    ideal = _vo_sites_run(tmp_path, "ideal", str(ideal_file))
    back = _vo_sites_run(tmp_path, "back", "short_trail", "--errors", "ideal")
    assert flag == bundled and back == ideal
    assert "stereo_calibration" in flag["kinds"] and "stereo_calibration" not in ideal["kinds"]
    assert flag["ate_rmse_m"] != ideal["ate_rmse_m"]
    scenario = tomllib.loads((tmp_path / "flag" / "scenario.toml").read_text())
    assert scenario["errors"]["profile"] == "realistic"


def test_the_truth_holds_the_true_angles_each_frame_was_taken_at(short_trail):
    """GroundTruth.mast_angles, which render takes each site frame at: a panorama frame's simulated
    pixels are the projections from those angles (median 0.37 px off, the pixel noise, over 11,710
    views of seed 2), not from the readings (11.9 px at a 1 deg resolution)."""
    scenario = _with_errors(short_trail, pan_tilt_resolution_deg=1.0)
    traverse, truth = simulate(scenario, 2)
    true_angles = truth.mast_angles
    rig = traverse.rig
    off = {"true": [], "read": []}
    for stop in traverse.stops:
        for frame, angles in zip(stop.panorama, true_angles.get(stop.index, ()), strict=False):
            seen = frame.observations
            for label, (pan, tilt) in (("true", angles), ("read", (frame.pan_rad, frame.tilt_rad))):
                world_T_left = truth.world_T_body[stop.index] @ rig.body_T_left(pan, tilt).matrix()
                p_cam = (truth.landmarks[seen.track_ids] - world_T_left[:3, 3]) @ world_T_left[:3, :3]
                uv = rig.wac.project(p_cam, distort=False)
                off[label].append(np.hypot(uv[:, 0] - seen.uvv[:, 0], uv[:, 1] - seen.uvv[:, 2]))
    true, read = np.concatenate(off["true"]), np.concatenate(off["read"])
    assert len(true) > 1000
    assert np.median(true) < 0.5  # the pixel noise: 0.3 px per axis
    assert np.median(read) > 3.0


def _along_tracks(frames: list[tuple[np.ndarray, np.ndarray]], lag: int) -> tuple[np.ndarray, np.ndarray]:
    """The errors of every feature `lag` frames apart on one track: (before, after) rows."""
    before, after = [], []
    for (ids_a, errors_a), (ids_b, errors_b) in zip(frames[:-lag], frames[lag:], strict=True):
        _, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
        before.append(errors_a[ia])
        after.append(errors_b[ib])
    return np.concatenate(before), np.concatenate(after)


def test_navigation_features_err_as_the_image_front_end_measured_against_the_renderers_depth():
    """The figures measured on rendered short_trail seeds 0 and 5 and denver_trail seed 1
    (scripts/vo_tracking_truth.py): 0.81-0.90 of the features that stay in view tracked on to the
    next stop; disparity error 0.57-0.59 px, correlated 0.70-0.73 one stop on along a track, 0.54
    at two, 0.42 at three, 0.17-0.19 at eight; the left pixel's error grows along the track,
    column 0.31-0.34, 0.50-0.54, 0.88-0.92 and 1.69-1.71 px after 1, 2, 4 and 8 stops, row 0.11,
    0.15, 0.22 and 0.42-0.44 px."""
    tracking = TrackingErrors(np.random.default_rng(5))
    landmarks = np.arange(20000)
    frames = [tracking(landmarks) for _ in range(13)]  # (track ids, errors of [u_left, u_right, v])
    survived = [np.isin(a, b).mean() for (a, _), (b, _) in zip(frames[:-1], frames[1:], strict=True)]
    assert np.mean(survived) == pytest.approx(0.85, abs=0.01)
    disparity = np.concatenate([errors[:, 0] - errors[:, 1] for _, errors in frames])
    assert np.std(disparity) == pytest.approx(0.58, abs=0.01)
    for lag, correlation in ((1, 0.70), (2, 0.54), (3, 0.42), (8, 0.19)):
        a, b = _along_tracks(frames, lag)
        assert np.corrcoef(a[:, 0] - a[:, 1], b[:, 0] - b[:, 1])[0, 1] == pytest.approx(correlation, abs=0.03), lag
    for lag, column, row in ((1, 0.325, 0.11), (2, 0.52, 0.15), (4, 0.90, 0.22), (8, 1.70, 0.43)):
        a, b = _along_tracks(frames, lag)
        assert np.std(b[:, 0] - a[:, 0]) == pytest.approx(column, rel=0.08), lag
        assert np.std(b[:, 2] - a[:, 2]) == pytest.approx(row, abs=0.04), lag
    # a feature the last frame did not see starts a new track where it is found, and so does one
    # whose track ended: the same landmark under a new track id
    before, _ = tracking(landmarks[:100])
    ids, errors = tracking(landmarks)
    np.testing.assert_array_equal(errors[100:, [0, 2]], 0.0)
    new = ids[:100] != before
    assert 5 < new.sum() < 30 and np.all(ids[:100] % TrackingErrors.ID_STRIDE == landmarks[:100])
    np.testing.assert_array_equal(errors[:100][new][:, [0, 2]], 0.0)
    assert np.all(errors[:100][~new][:, [0, 2]] != 0.0)


def test_measured_tracking_moves_the_navigation_pixels_alone():
    """The same landmarks (under their track ids), odometry and panoramas as without it; every
    navigation frame's pixels moved."""
    short_trail = _short_trail(None)
    ideal, _ = simulate(short_trail, 1)
    tracked, _ = simulate(_with_errors(short_trail, stereo_tracking="measured"), 1)
    for a, b in zip(ideal.stops, tracked.stops, strict=True):
        np.testing.assert_array_equal(a.stereo.track_ids, b.stereo.track_ids % TrackingErrors.ID_STRIDE)
        assert len(a.stereo) == 0 or np.abs(a.stereo.uvv - b.stereo.uvv).max() > 0.05
        for fa, fb in zip(a.panorama, b.panorama, strict=True):
            np.testing.assert_array_equal(fa.observations.uvv, fb.observations.uvv)


def test_the_vo_claims_what_the_tracking_errors_do_over_a_site_spacing():
    """Under the measured tracking, a chain of 30 VO steps (about a site spacing) errs by what
    its composed covariance claims once the steps' sigmas are scaled (vo_sigma_scale): in
    heading, forward and lateral its normalized error is near 1, where the unscaled steps claim
    half of it or less. The drawn calibration's share is taken out through the steps'
    sensitivity (the graph estimates it)."""
    import gtsam

    from pancam_graph.frontend.motion import VoMotions
    from pancam_graph.geometry.calibration_error import NAMES
    from pancam_graph.graph.tie_gate import RelativePose

    scenario = _short_trail({"profile": "realistic"})
    assert scenario.estimator.vo_sigma_scale is not None
    unscaled = scenario.estimator.model_copy(update={"vo_sigma_scale": None})
    normalized = {"scaled": [], "unscaled": []}
    for seed in (0, 1, 2, 3):
        traverse, truth = simulate(scenario, seed)
        drawn = np.array([truth.kinds["stereo_calibration"][name] for name in NAMES])
        for label, estimator in (("scaled", scenario.estimator), ("unscaled", unscaled)):
            motions = VoMotions.estimate(traverse, estimator).motions
            for a in range(0, len(motions) - 30, 10):  # overlapping chains
                chain = motions[a + 1:a + 31]
                if any(m is None or m.source != "vo" or m.calibration_sensitivity is None for m in chain):
                    continue
                relative = RelativePose.compose([(m.prev_T_curr, m.covariance) for m in chain],
                                                [m.calibration_sensitivity for m in chain])
                true = gtsam.Pose3(np.linalg.inv(truth.world_T_body[a]) @ truth.world_T_body[a + 30])
                error = gtsam.Pose3.Logmap(true.between(relative.a_T_b)) - relative.calibration_sensitivity @ drawn
                normalized[label].append(error / np.sqrt(np.diag(relative.covariance)))
    rms = {label: np.sqrt(np.mean(np.square(z), axis=0)) for label, z in normalized.items()}
    assert len(normalized["scaled"]) >= 25
    heading_forward_lateral = [2, 3, 4]
    assert np.all((rms["scaled"][heading_forward_lateral] > 0.5) & (rms["scaled"][heading_forward_lateral] < 1.4))
    assert np.max(rms["unscaled"][heading_forward_lateral]) > 1.5


def test_a_noise_seed_draws_the_measurements_anew_over_the_same_world():
    """noise_seed: the same path, landmarks, sites, drawn calibration and mast angles, and another
    draw of the pixels, whose errors about the truth are as large as the seed's own."""
    scenario = _short_trail({"profile": "realistic"})
    own, own_truth = simulate(scenario, 3)
    again, again_truth = simulate(scenario.model_copy(update={"noise_seed": 7}), 3)
    np.testing.assert_array_equal(own_truth.world_T_body, again_truth.world_T_body)
    # the field's landmarks (measured ties append their own fresh ones after them, a draw of the ties)
    np.testing.assert_array_equal(own_truth.landmarks[:1000], again_truth.landmarks[:1000])
    np.testing.assert_array_equal(own_truth.kinds["stereo_calibration"], again_truth.kinds["stereo_calibration"])
    assert own_truth.mast_angles == again_truth.mast_angles
    assert [s.site_id for s in own.stops] == [s.site_id for s in again.stops]
    rig = own.rig

    def pixel_errors(traverse, truth) -> np.ndarray:
        """Each navigation view's column error about the true projection through the drawn pair."""
        errors = []
        for stop in traverse.stops[1:40]:
            seen = stop.stereo
            world_T_left = truth.world_T_body[stop.index] @ rig.body_T_left(0.0, traverse.traverse_tilt_rad).matrix()
            p_cam = (truth.landmarks[seen.track_ids % 2**32] - world_T_left[:3, 3]) @ world_T_left[:3, :3]
            errors.append(rig.wac.project(p_cam, distort=False)[:, 0] - seen.uvv[:, 0])
        return np.concatenate(errors)

    a, b = pixel_errors(own, own_truth), pixel_errors(again, again_truth)
    assert len(a) > 500 and len(b) > 500
    assert not np.array_equal(a[:100], b[:100])
    spread_a, spread_b = (1.4826 * np.median(np.abs(x - np.median(x))) for x in (a, b))
    assert 0.8 < spread_a / spread_b < 1.25
