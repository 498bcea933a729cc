"""Calibration readers on KITTI's real calibration (drive 2011_09_26) written in each format:
the rectified baseline agrees with KITTI's own rectification; bad files name the field."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from pancam_graph.errors import InputError
from pancam_graph.formats.calibration import (
    read_camera_info_pair,
    read_kalibr_camchain,
    read_opencv_yaml,
    read_stereo_calibration,
)
from pancam_graph.formats.kitti import read_cam_to_cam

pytestmark = pytest.mark.real_data

CALIB = Path(__file__).parents[1] / "data" / "real" / "kitti_raw" / "2011_09_26" / "calib_cam_to_cam.txt"


@pytest.fixture(scope="module")
def kitti():
    """Unrectified cameras 02 (left) and 03 (right) of the real KITTI calibration file."""
    e = {}
    for line in CALIB.read_text().splitlines():
        key, _, value = line.partition(":")
        try:
            e[key.strip()] = np.array([float(v) for v in value.split()])
        except ValueError:
            continue
    r02, r03 = e["R_02"].reshape(3, 3), e["R_03"].reshape(3, 3)
    rotation = r03 @ r02.T  # left-camera points into the right camera
    return {"K1": e["K_02"].reshape(3, 3), "D1": e["D_02"], "K2": e["K_03"].reshape(3, 3), "D2": e["D_03"],
            "R": rotation, "T": e["T_03"] - rotation @ e["T_02"], "size": (1392, 512),
            "rectified": read_cam_to_cam(CALIB)}


def _opencv_yaml(path: Path, k: dict, skip: str = "") -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name in ("K1", "D1", "K2", "D2", "R", "T"):
        if name != skip:
            fs.write(name, np.atleast_2d(k[name]))
    fs.write("image_width", k["size"][0])
    fs.write("image_height", k["size"][1])
    fs.release()
    return path


def _camchain(k: dict, model: str = "pinhole") -> dict:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = k["R"], k["T"]

    def cam(kk, d):
        return {"camera_model": model, "intrinsics": [float(kk[0, 0]), float(kk[1, 1]), float(kk[0, 2]),
                                                      float(kk[1, 2])],
                "distortion_model": "radtan", "distortion_coeffs": d[:4].tolist(),
                "resolution": list(k["size"]), "rostopic": "/cam"}

    return {"cam0": cam(k["K1"], k["D1"]), "cam1": {**cam(k["K2"], k["D2"]), "T_cn_cnm1": t.tolist()}}


def test_opencv_yaml_and_kalibr_rectify_to_kittis_baseline(kitti, tmp_path):
    ours = read_opencv_yaml(_opencv_yaml(tmp_path / "stereo.yml", kitti))
    np.testing.assert_allclose(ours.k_right, kitti["K2"])
    assert ours.size == (1392, 512)
    rectified = ours.rectified()
    # KITTI's own rectification (P_rect_02/03) says 0.53273 m; OpenCV's, from the raw calibration, agrees.
    assert rectified.baseline_m == pytest.approx(kitti["rectified"].baseline_m, abs=1e-4)
    assert read_stereo_calibration(tmp_path / "stereo.yml")[1] == rectified
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(yaml.safe_dump(_camchain(kitti)))
    kalibr = read_kalibr_camchain(camchain)
    np.testing.assert_allclose(kalibr.translation, kitti["T"])
    # Kalibr's radtan has no k3: KITTI's k3 is dropped, the geometry of the pair is the same.
    assert kalibr.rectified().baseline_m == pytest.approx(rectified.baseline_m, abs=1e-9)
    assert read_stereo_calibration(camchain)[1].baseline_m == pytest.approx(rectified.baseline_m, abs=1e-9)


def _camera_info(p: np.ndarray, size, drop: str = "") -> dict:
    info = {"image_width": size[0], "image_height": size[1], "camera_name": "kitti", "distortion_model": "plumb_bob",
            "camera_matrix": {"rows": 3, "cols": 3, "data": p[:, :3].ravel().tolist()},
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": p.ravel().tolist()}}
    info.pop(drop, None)
    return info


def test_camera_info_pair_gives_kittis_rectified_model(kitti, tmp_path):
    e = {}
    for line in CALIB.read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("P_rect_02", "P_rect_03"):
            e[key] = np.array([float(v) for v in value.split()]).reshape(3, 4)
    # camera_info's P is relative to the left camera; KITTI's is relative to camera 0.
    left, right = e["P_rect_02"].copy(), e["P_rect_03"].copy()
    right[0, 3] -= left[0, 3]
    left[0, 3] = 0.0
    for name, p in (("left.yaml", left), ("right.yaml", right)):
        (tmp_path / name).write_text(yaml.safe_dump(_camera_info(p, (1242, 375))))
    stereo = read_camera_info_pair(tmp_path / "left.yaml", tmp_path / "right.yaml")
    assert stereo.baseline_m == pytest.approx(kitti["rectified"].baseline_m, rel=1e-9)
    assert stereo.camera.fx == kitti["rectified"].camera.fx and stereo.camera.width == 1242
    # a defect of one file is reported in that file's name
    for name, p in (("left.yaml", left), ("right.yaml", right)):
        bad = p.copy()
        bad[0, 2] = 5000.0  # the principal point off the image
        (tmp_path / name).write_text(yaml.safe_dump(_camera_info(bad, (1242, 375))))
        with pytest.raises(InputError, match=rf"^{re.escape(str(tmp_path / name))}: .* principal point \(5000,"):
            read_camera_info_pair(tmp_path / "left.yaml", tmp_path / "right.yaml")
        (tmp_path / name).write_text(yaml.safe_dump(_camera_info(p, (1242, 375))))


def test_missing_calibration_field_is_named(kitti, tmp_path):
    with pytest.raises(InputError, match=r"stereo.yml: missing field 'D2'"):
        read_opencv_yaml(_opencv_yaml(tmp_path / "stereo.yml", kitti, skip="D2"))
    (tmp_path / "left.yaml").write_text(yaml.safe_dump(_camera_info(np.eye(3, 4), (10, 10), drop="projection_matrix")))
    with pytest.raises(InputError, match=r"left.yaml: missing field 'projection_matrix'"):
        read_camera_info_pair(tmp_path / "left.yaml", tmp_path / "left.yaml")
    chain = _camchain(kitti)
    del chain["cam1"]["T_cn_cnm1"]
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(chain))
    with pytest.raises(InputError, match=r"camchain.yaml: missing field 'cam1.T_cn_cnm1'"):
        read_kalibr_camchain(tmp_path / "camchain.yaml")
    with pytest.raises(InputError, match=r"nothing.yml: no such calibration file"):
        read_opencv_yaml(tmp_path / "nothing.yml")


def test_unknown_kalibr_camera_model_is_an_error(kitti, tmp_path):
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(_camchain(kitti, model="omni")))
    with pytest.raises(InputError, match=r"camchain.yaml: cam0.camera_model: 'omni' is not supported \(supported: "
                                         r"pinhole\)"):
        read_kalibr_camchain(tmp_path / "camchain.yaml")


def test_the_rectified_camera_frame_is_raw_R_rectified_of_the_calibrated_one(kitti):
    """Points seen by KITTI's real unrectified pair 02/03 (distortion, 0.4 deg misalignment),
    rectified with `rectification_maps`' model: same row in both images, and triangulated in
    the rectified camera they are the original points once turned by raw_R_rectified."""
    from pancam_graph.geometry.rig import triangulate_rectified
    from pancam_graph.geometry.stereo_pair import StereoCalibration

    k = kitti
    calibration = StereoCalibration("kitti", k["K1"], k["D1"], k["K2"], k["D2"], k["size"], k["R"], k["T"])
    assert not calibration.is_rectified
    rectified = calibration.rectified()
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-8, 8, 200), rng.uniform(-2, 2, 200), rng.uniform(6, 40, 200)])
    left, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), k["K1"], k["D1"])
    right, _ = cv2.projectPoints(points, cv2.Rodrigues(k["R"])[0], k["T"], k["K2"], k["D2"])
    w, h = k["size"]
    seen = np.all((left.reshape(-1, 2) >= 0) & (left.reshape(-1, 2) < (w, h)) & (right.reshape(-1, 2) >= 0)
                  & (right.reshape(-1, 2) < (w, h)), axis=1)
    assert seen.sum() > 100
    points, left, right = points[seen], left[seen], right[seen]
    r1, r2, p1, p2, *_ = cv2.stereoRectify(k["K1"], k["D1"], k["K2"], k["D2"], k["size"], k["R"],
                                           k["T"].reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    ul = cv2.undistortPoints(left, k["K1"], k["D1"], R=r1, P=p1, criteria=criteria).reshape(-1, 2)
    ur = cv2.undistortPoints(right, k["K2"], k["D2"], R=r2, P=p2, criteria=criteria).reshape(-1, 2)
    assert np.max(np.abs(ul[:, 1] - ur[:, 1])) < 0.01
    x_rect = triangulate_rectified(ul[:, 0], ur[:, 0], ul[:, 1], rectified.camera, rectified.baseline_m)
    back = x_rect @ rectified.raw_R_rectified.T
    assert np.max(np.linalg.norm(back - points, axis=1) / points[:, 2]) < 1e-4
    # ... while ignoring the turn puts them centimetres off at 40 m
    assert np.max(np.linalg.norm(x_rect - points, axis=1)) > 0.05


def test_a_preset_rig_with_a_calibrated_pair_reads_back_unchanged(short_scenario, tmp_path):
    """What `track` writes for a rendered (raw, calibrated) folder: the preset's mast and HRC,
    the rectified pair and the turn rectification gave it, all read back as they were."""
    from dataclasses import replace

    from pancam_graph.config import EstimatorConfig
    from pancam_graph.geometry.rig import rig_preset
    from pancam_graph.sim import simulate
    from pancam_graph.store.observation_folder import read_observations
    from pancam_graph.store.observation_writer import write_observations

    traverse, _ = simulate(short_scenario, 0)
    rotation = cv2.Rodrigues(np.array([0.01, -0.002, 0.003]))[0]
    rig = replace(rig_preset("exomars"), wac=replace(traverse.rig.wac, fx=1694.5, fy=1694.5, cx=511.2),
                  baseline_m=0.5012, raw_R_rectified=tuple(rotation.ravel().tolist()))
    traverse = replace(traverse, rig=rig)
    write_observations(tmp_path / "obs", traverse, EstimatorConfig(), 0)
    back = read_observations(tmp_path / "obs").traverse.rig
    assert back.hrc == rig.hrc and back.mast_height_m == rig.mast_height_m
    assert back.wac.fx == pytest.approx(1694.5) and back.baseline_m == pytest.approx(0.5012)
    np.testing.assert_allclose(back.rectification(), rotation, atol=1e-12)


KATWIJK = Path(__file__).parents[1] / "data" / "real" / "katwijk_pancam_calib"


def test_katwijk_pancam_matlab_calibration_reads_with_its_published_baseline_and_focal_length():
    import scipy.io

    from pancam_graph.formats.calibration import read_matlab_stereo_parameters

    path = KATWIJK / "PanCam_calibstruct.mat"
    c = read_matlab_stereo_parameters(path, image_size=(1280, 960))
    assert c.baseline_m * 1e3 == pytest.approx(502.44, abs=0.01)  # published: about 502.4 mm
    assert c.k_left[0, 0] == pytest.approx(1421.16, abs=0.01) and c.k_left[1, 1] == pytest.approx(1429.54, abs=0.01)
    assert c.k_left[0, 2] == pytest.approx(654.639 - 1.0, abs=1e-3)  # MATLAB pixels are 1-based
    np.testing.assert_allclose(c.d_left[:2], [-0.26445, 0.26257], atol=1e-5)
    # The file's own fundamental matrix, rebuilt from K, R and T in OpenCV's conventions (1-based
    # pixels again): it checks the transposed K and R, the pixel shift and the units together.
    t = c.translation
    cross = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    f = np.linalg.inv(c.k_right).T @ cross @ c.rotation @ np.linalg.inv(c.k_left)
    one_based = np.array([[1.0, 0, -1], [0, 1, -1], [0, 0, 1]])
    f = one_based.T @ f @ one_based
    matlab = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)["stereoParams"].FundamentalMatrix
    np.testing.assert_allclose(f / np.linalg.norm(f), matlab / np.linalg.norm(matlab), atol=1e-9)
    # the navigation pair's file also holds MATLAB's `ans`: the stereoParams struct is the one read
    loc = read_matlab_stereo_parameters(KATWIJK / "LocCam_calibstruct.mat", image_size=(1024, 768))
    assert loc.baseline_m * 1e3 == pytest.approx(120.08, abs=0.01)
    assert loc.k_left[0, 0] == pytest.approx(834.26, abs=0.01)


def test_the_katwijk_pancam_rig_preset_is_the_calibration_file():
    from pancam_graph.formats.calibration import read_raw_calibration
    from pancam_graph.geometry.rig import rig_preset

    read = read_raw_calibration(KATWIJK / "PanCam_calibstruct.mat", image_size=(1280, 960))
    rectified = read.rectified()
    rig = rig_preset("katwijk_pancam")
    assert rig.wac == rectified.camera and rig.baseline_m == rectified.baseline_m
    np.testing.assert_allclose(rig.rectification(), rectified.raw_R_rectified, atol=1e-12)
    # the rectified left camera's x axis points along the baseline, at the right camera's centre
    right_centre = -read.rotation.T @ read.translation
    np.testing.assert_allclose(rig.rectification()[:, 0], right_centre / np.linalg.norm(right_centre), atol=1e-9)


def test_a_matlab_calibration_without_image_size_or_of_the_wrong_kind_is_named(tmp_path):
    from pancam_graph.formats.calibration import read_raw_calibration

    path = KATWIJK / "PanCam_calibstruct.mat"
    with pytest.raises(InputError, match=r"PanCam_calibstruct.mat: CameraParameters1.ImageSize is empty.*"
                                         r"reach x = 1196, y = 921"):
        read_raw_calibration(path)
    bad = tmp_path / "calib.mat"
    bad.write_bytes(b"not a mat file at all")
    with pytest.raises(InputError, match="calib.mat: not a MATLAB .mat file"):
        read_raw_calibration(bad)


def _broken(kitti: dict, name: str, index, value) -> dict:
    k = {key: (v.copy() if isinstance(v, np.ndarray) else v) for key, v in kitti.items()}
    k[name][index] = value
    return k


@pytest.mark.parametrize("name,index,value,words", [
    ("K1", (1, 1), 0.0, "left camera focal lengths fx = 959.791, fy = 0 px must be positive"),
    ("K2", (0, 0), 0.0, "right camera focal lengths fx = 0"),
    ("K1", (0, 2), np.nan, "K1 has a value that is not a finite number"),
    ("K2", (1, 2), 2000.0, "right camera principal point (695.752, 2000) px is off the 1392 x 512 image"),
    ("T", slice(None), 0.0, "baseline 0 m: expected a stereo pair's"),
    ("R", (0, 0), -1.0, "R is not a rotation matrix"),
])
def test_a_calibration_vo_cannot_use_is_refused_naming_what(kitti, tmp_path, name, index, value, words):
    """Each once ran 'successfully' as dead reckoning (VO failing at every stop) or crashed in
    OpenCV (issue 15)."""
    broken = _broken(kitti, name, index, value)
    with pytest.raises(InputError) as error:
        read_opencv_yaml(_opencv_yaml(tmp_path / "stereo.yml", broken))
    assert "stereo.yml: " + words in str(error.value)
    if name in ("K1", "K2") and not np.isnan(value):  # Kalibr carries the same intrinsics
        (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(_camchain(broken)))
        with pytest.raises(InputError, match="camchain.yaml: "):
            read_kalibr_camchain(tmp_path / "camchain.yaml")


def test_a_kalibr_nan_is_named_not_an_opencv_traceback(kitti, tmp_path):
    chain = _camchain(kitti)
    chain["cam0"]["distortion_coeffs"][1] = float("nan")
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(chain))
    with pytest.raises(InputError, match=r"camchain.yaml: D1 has a value that is not a finite number"):
        read_stereo_calibration(tmp_path / "camchain.yaml")


def test_a_matlab_file_that_crashes_scipys_reader_is_refused_naming_it():
    # found by fuzzing: scipy's loadmat dies of a segfault on this file (tests/data/fuzz/README.md)
    from pancam_graph.formats.calibration import read_matlab_stereo_parameters

    path = Path(__file__).parents[1] / "data" / "fuzz" / "loadmat_segfault.mat"
    with pytest.raises(InputError, match=r"loadmat_segfault\.mat: reading it crashed scipy's MATLAB reader"):
        read_matlab_stereo_parameters(path, image_size=(1280, 960))
