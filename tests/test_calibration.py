"""Calibration readers on KITTI's real calibration (drive 2011_09_26) written in each format:
the rectified baseline agrees with KITTI's own rectification; bad files name the field."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from pancam_graph.errors import InputError
from pancam_graph.io.calibration import (
    read_camera_info_pair,
    read_kalibr_camchain,
    read_opencv_yaml,
    read_stereo_calibration,
)
from pancam_graph.io.kitti import read_cam_to_cam

CALIB = Path(__file__).parent / "data" / "real" / "kitti_raw" / "2011_09_26" / "calib_cam_to_cam.txt"


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
    assert read_stereo_calibration(tmp_path / "stereo.yml") == rectified
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(yaml.safe_dump(_camchain(kitti)))
    kalibr = read_kalibr_camchain(camchain)
    np.testing.assert_allclose(kalibr.translation, kitti["T"])
    # Kalibr's radtan has no k3: KITTI's k3 is dropped, the geometry of the pair is the same.
    assert kalibr.rectified().baseline_m == pytest.approx(rectified.baseline_m, abs=1e-9)
    assert read_stereo_calibration(camchain).baseline_m == pytest.approx(rectified.baseline_m, abs=1e-9)


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
