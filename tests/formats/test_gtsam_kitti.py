"""KITTI sequence 00's real stereo tracks and GPS as GTSAM's wheel ships them (issue 33): the
reader against the files, the start fitted on the example's own VO or on KITTI's ground truth
(tests/data/real/kitti00_ground_truth), and our VO on these tracks judged against the truth and
the real GPS it was never fitted to."""

from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares

from pancam_graph import api
from pancam_graph.config import EstimatorConfig
from pancam_graph.errors import InputError
from pancam_graph.evaluation.gps_check import antenna_at_times, gps_enu
from pancam_graph.formats.gtsam_kitti import (
    FILES,
    TRUTH_FIRST_FRAME,
    example_data_folder,
    fit_start,
    fit_start_on_truth,
    kitti00_on_truth,
    read_kitti00_example,
    read_kitti00_truth,
)
from pancam_graph.store.documents import metrics_document
from pancam_graph.store.observation_writer import write_observations

TRUTH = Path(__file__).parents[1] / "data" / "real" / "kitti00_ground_truth"


@pytest.fixture(scope="module")
def example():
    return read_kitti00_example()


@pytest.fixture(scope="module")
def truth():
    return read_kitti00_truth(TRUTH)


def test_the_reader_gives_the_wheel_files_tracks_calibration_and_gps(example):
    assert len(example.frames) == 135 and sum(len(o) for o in example.observations) == 88781
    assert list(example.frames[92:96]) == [92, 93, 95, 97]  # the example left every other frame out here
    assert (example.fx, example.cx, example.cy) == (718.856, 607.1928, 185.2157)
    assert example.baseline_m == pytest.approx(0.5371657, abs=1e-7)
    assert len(example.gps_times_s) == 470
    assert example.frame_step_s == pytest.approx(0.1037, abs=2e-4)  # KITTI's 10.4 Hz over the whole drive
    uvv = np.vstack([o.uvv for o in example.observations])
    assert np.all(uvv[:, 0] >= uvv[:, 1])  # disparity never negative: left and right are the right way round


def test_a_damaged_file_is_named_with_its_line(tmp_path):
    for name in FILES:
        (tmp_path / name).write_bytes((example_data_folder() / name).read_bytes())
    lines = (tmp_path / FILES[0]).read_text().splitlines()
    lines[4] = "0 7 322.5 north 11.7 -6.6 -4.1 16.8"
    (tmp_path / FILES[0]).write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"VO_stereo_factors00.txt: line 5: expected numbers"):
        read_kitti00_example(tmp_path)


def test_the_start_fitted_on_the_example_s_vo_lies_on_the_gps(example):
    start = fit_start(example)
    assert start.fixes == 14
    assert start.rms_m < 0.5  # RTK-grade fixes against a decent VO over 15 s
    assert abs(start.clock_offset_s) < 0.5  # one clock logged both
    assert abs(start.scale - 1.0) < 0.05
    assert np.rad2deg(start.sigmas[2]) < 0.5 and start.sigmas[3] < 0.5


def test_the_ground_truth_lies_on_the_gps_once_its_clock_offset_is_fitted(example, truth):
    assert len(truth.times_s) == 4541 and np.allclose(truth.world_T_camera[0], np.eye(4), atol=1e-6)
    assert np.median(np.diff(truth.times_s)) == pytest.approx(0.1037, abs=2e-4)
    start = fit_start_on_truth(example, truth)
    assert start.fixes == 469  # the whole drive
    assert 0.35 < start.clock_offset_s < 0.55
    assert start.rms_m < 0.5  # RTK against KITTI's truth: about 0.35 m
    assert np.allclose(start.world_T_body, start.truth_world_T_body[0])


def test_the_truth_steps_evenly_where_both_vos_see_the_car_accelerate(example, truth):
    """Why the truth is used from frame 16 (TRUTH_FIRST_FRAME) on."""
    first = example.frames[example.frames <= TRUTH_FIRST_FRAME]
    truth_steps = np.linalg.norm(np.diff(truth.world_T_camera[first, :3, 3], axis=0), axis=1)
    vo_steps = np.linalg.norm(np.diff(example.example_world_T_camera[:len(first), :3, 3], axis=0), axis=1)
    assert np.ptp(truth_steps[:14]) < 0.005  # 0.860 m every frame
    assert vo_steps[13] / vo_steps[0] > 1.2  # 0.68 m rising to 0.86 m
    later = example.from_frame(TRUTH_FIRST_FRAME)
    truth_length = np.sum(np.linalg.norm(np.diff(truth.world_T_camera[later.frames, :3, 3], axis=0), axis=1))
    vo_length = np.sum(np.linalg.norm(np.diff(later.example_world_T_camera[:, :3, 3], axis=0), axis=1))
    assert vo_length / truth_length == pytest.approx(1.0, abs=0.01)


def test_a_truth_with_missing_frames_or_times_that_go_back_is_named(tmp_path):
    (tmp_path / "poses.txt.gz").write_bytes((TRUTH / "poses.txt.gz").read_bytes())
    times = (TRUTH / "times.txt").read_text().splitlines()
    (tmp_path / "times.txt").write_text("\n".join(times[:-1]))
    with pytest.raises(InputError, match=r"times.txt: 4540 frames; sequence 00 has 4541"):
        read_kitti00_truth(tmp_path)
    times[7] = times[5]
    (tmp_path / "times.txt").write_text("\n".join(times))
    with pytest.raises(InputError, match=r"times.txt: line 8: time does not increase"):
        read_kitti00_truth(tmp_path)
    (tmp_path / "poses.txt.gz").write_bytes((TRUTH / "poses.txt.gz").read_bytes()[:5000])
    with pytest.raises(InputError, match=r"poses.txt.gz: not a whole gzip file"):
        read_kitti00_truth(tmp_path)


@pytest.fixture(scope="module")
def runs(example, truth, tmp_path_factory):
    """vo on the tracks from frame 16 against the truth (the folder carries it) with the real-image
    model and with white noise, and against the GPS alone (the same folder without the truth)."""
    traverse, ground_truth, _ = kitti00_on_truth(example, truth)
    with_truth, gps_only = tmp_path_factory.mktemp("kitti00_truth"), tmp_path_factory.mktemp("kitti00_gps")
    write_observations(with_truth, traverse, EstimatorConfig(vo_error_model="real_images"), seed=0, truth=ground_truth)
    write_observations(gps_only, traverse, EstimatorConfig(vo_error_model="real_images"), seed=0)
    out = tmp_path_factory.mktemp("out")
    return {name: api.run(folder, out=out / name, configs=("vo",), figures=False, processes=1,
                          vo_error_model=model).result
            for name, folder, model in (("truth", with_truth, "real_images"), ("gps", gps_only, "real_images"),
                                        ("truth_white", with_truth, "pixel_noise"))}


@pytest.mark.slow
def test_vo_on_the_real_tracks_ends_within_one_percent_of_the_truth_and_its_covariance_holds(runs):
    result = runs["truth"]
    assert result.estimator.vo_error_model == "real_images"
    vo = result.configurations["vo"]
    truth = result.truth.world_T_body
    length = np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))
    assert length == pytest.approx(98.6, abs=0.5)
    end = np.linalg.norm(vo.world_T_body[-1, :3, 3] - truth[-1, :3, 3])
    assert end <= 0.01 * length  # 0.60 m
    assert vo.nees.against == "truth" and vo.nees.last <= 11.3
    assert vo.nees.outside_99_fraction <= 0.05
    assert 0.3 < vo.consistency.anees <= 3.0  # 1.6


@pytest.mark.slow
def test_vo_on_the_real_tracks_follows_the_real_gps_and_its_covariance_holds(runs):
    result = runs["gps"]
    vo = result.configurations["vo"]
    times, fixes = gps_enu(result.traverse)
    inside = (times >= result.traverse.stops[0].time_s) & (times <= result.traverse.stops[-1].time_s)
    antenna = antenna_at_times(result.traverse, vo.world_T_body, times[inside])
    fixes = fixes[inside]
    driven = np.sum(np.linalg.norm(np.diff(vo.world_T_body[:, :3, 3], axis=0), axis=1))
    # the last fix within 1 % of the distance driven (0.77 m of 98 m)
    assert np.linalg.norm(antenna[-1] - fixes[-1]) <= 0.01 * driven
    # shape and scale of the VO against the GPS
    centre = antenna.mean(axis=0)

    def moved(x):
        c, s = np.cos(x[0]), np.sin(x[0])
        return np.exp(x[4]) * (antenna - centre) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + centre + x[1:4]

    fit = least_squares(lambda x: (moved(x) - fixes).ravel(), np.zeros(5))
    assert abs(np.exp(fit.x[4]) - 1.0) < 0.01  # distance within 1 % of the GPS's
    assert np.sqrt(np.mean(np.sum((moved(fit.x) - fixes)[:, :2] ** 2, axis=1))) < 0.5
    # the covariance against the fixes: every fix inside its 99 % ellipsoid, ANEES near 1
    assert vo.nees.against == "gps" and len(vo.nees.nees) == 14
    assert vo.nees.outside_99_fraction <= 0.05
    assert 0.3 < vo.nees.anees < 3.0
    entry = metrics_document(result)["configs"]["vo"]  # no truth, no CRLB: the ANEES is the fixes'
    assert entry["nees_against"] == "gps" and entry["nees_samples"] == 14 and entry["anees"] == vo.nees.anees


@pytest.mark.slow
def test_white_pixel_noise_is_over_confident_on_the_same_tracks(runs):
    vo = runs["truth_white"].configurations["vo"]  # against the truth: ANEES 178, 97 % of stops outside
    assert vo.nees.against == "truth" and vo.consistency.anees > 30.0 and vo.nees.outside_99_fraction > 0.5


def test_a_frame_number_that_is_not_a_whole_number_is_named(tmp_path):
    for name in FILES:
        (tmp_path / name).write_bytes((example_data_folder() / name).read_bytes())
    lines = (tmp_path / FILES[2]).read_text().splitlines()
    lines[2] = "1e308" + lines[2][1:]
    (tmp_path / FILES[2]).write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"VO_camera_poses00.txt: line 3: frame 1e\+308: expected a whole number"):
        read_kitti00_example(tmp_path)
