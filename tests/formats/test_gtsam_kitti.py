"""KITTI sequence 00's real stereo tracks and GPS as GTSAM's wheel ships them (issue 33): the
reader against the files, the start fitted on the example's own VO, and our VO on these tracks
judged against the real GPS it was never fitted to."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from pancam_graph import api
from pancam_graph.config import EstimatorConfig
from pancam_graph.errors import InputError
from pancam_graph.evaluation.gps_check import antenna_at_times, gps_enu
from pancam_graph.formats.gtsam_kitti import (
    FILES,
    example_data_folder,
    fit_start,
    kitti00_traverse,
    read_kitti00_example,
)
from pancam_graph.solve.results import metrics_document
from pancam_graph.store.observation_folder import write_observations


@pytest.fixture(scope="module")
def example():
    return read_kitti00_example()


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


@pytest.fixture(scope="module")
def runs(example, tmp_path_factory):
    folder = tmp_path_factory.mktemp("kitti00")
    write_observations(folder, kitti00_traverse(example, fit_start(example)),
                       EstimatorConfig(vo_error_model="real_images"), seed=0)
    out = tmp_path_factory.mktemp("out")
    return {model: api.run(folder, out=out / model, configs=("vo",), figures=False, processes=1,
                           vo_error_model=model).result
            for model in ("real_images", "pixel_noise")}


@pytest.mark.slow
def test_vo_on_the_real_tracks_follows_the_real_gps_and_its_covariance_holds(runs):
    result = runs["real_images"]
    assert result.estimator.vo_error_model == "real_images"
    vo = result.configurations["vo"]
    times, fixes = gps_enu(result.traverse)
    inside = (times >= result.traverse.stops[0].time_s) & (times <= result.traverse.stops[-1].time_s)
    antenna = antenna_at_times(result.traverse, vo.world_T_body, times[inside])
    fixes = fixes[inside]
    # shape and scale of the VO against the GPS (the start pose is the example's, not ours)
    centre = antenna.mean(axis=0)

    def moved(x):
        c, s = np.cos(x[0]), np.sin(x[0])
        return np.exp(x[4]) * (antenna - centre) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + centre + x[1:4]

    fit = least_squares(lambda x: (moved(x) - fixes).ravel(), np.zeros(5))
    assert abs(np.exp(fit.x[4]) - 1.0) < 0.02  # distance within 2 % of the GPS's
    assert np.sqrt(np.mean(np.sum((moved(fit.x) - fixes)[:, :2] ** 2, axis=1))) < 0.5
    assert vo.metrics_vs_gps.closure_error_2d_m < 3.0  # about 1.9 m over about 110 m driven
    # the covariance against the fixes: every fix inside its 99 % ellipsoid, ANEES near 1
    assert vo.nees.against == "gps" and len(vo.nees.nees) == 14
    assert vo.nees.outside_99_fraction <= 0.05
    assert 0.3 < vo.nees.anees < 3.0
    entry = metrics_document(result)["configs"]["vo"]  # no truth, no CRLB: the ANEES is the fixes'
    assert entry["nees_against"] == "gps" and entry["nees_samples"] == 14 and entry["anees"] == vo.nees.anees


@pytest.mark.slow
def test_white_pixel_noise_is_over_confident_on_the_same_tracks(runs):
    vo = runs["pixel_noise"].configurations["vo"]
    assert vo.nees.anees > 3.0 and vo.nees.outside_99_fraction > 0.3


def test_a_frame_number_that_is_not_a_whole_number_is_named(tmp_path):
    for name in FILES:
        (tmp_path / name).write_bytes((example_data_folder() / name).read_bytes())
    lines = (tmp_path / FILES[2]).read_text().splitlines()
    lines[2] = "1e308" + lines[2][1:]
    (tmp_path / FILES[2]).write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"VO_camera_poses00.txt: line 3: frame 1e\+308: expected a whole number"):
        read_kitti00_example(tmp_path)
