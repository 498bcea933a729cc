"""Stereo calibration files: OpenCV YAML, Kalibr camchain, ROS camera_info; and the rectified
stereo model the back-end works in (OpenCV's stereoRectify when the pair is not rectified).

Every reader names the file and the field it could not find or understand.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..rig import Camera

KALIBR_CAMERA_MODELS = ("pinhole",)
KALIBR_DISTORTION_MODELS = ("radtan", "none")  # OpenCV's plumb-bob order (k1, k2, p1, p2)
ROS_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "")


@dataclass(frozen=True)
class RectifiedStereo:
    """A rectified stereo pair: the left camera's pinhole model and the baseline (m), and the
    rectified left camera's axes in the calibrated (raw) left camera's frame (rectification turns
    the camera a little; identity when the pair came rectified)."""

    camera: Camera
    baseline_m: float
    raw_R_rectified: np.ndarray = field(default_factory=lambda: np.eye(3), compare=False)


@dataclass(frozen=True)
class RectificationMaps:
    """Pixel maps taking raw (distorted, unaligned) images to the rectified pair (cv2.remap)."""

    left: tuple[np.ndarray, np.ndarray]
    right: tuple[np.ndarray, np.ndarray]

    def __call__(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (cv2.remap(left, *self.left, cv2.INTER_LINEAR),
                cv2.remap(right, *self.right, cv2.INTER_LINEAR))


@dataclass(frozen=True)
class StereoCalibration:
    """Two calibrated cameras as OpenCV's stereoCalibrate gives them: intrinsics K, distortion D
    (OpenCV order), image size (width, height), and R, T taking left-camera points to the
    right camera (x_right = R x_left + T)."""

    source: str
    k_left: np.ndarray
    d_left: np.ndarray
    k_right: np.ndarray
    d_right: np.ndarray
    size: tuple[int, int]
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.translation))

    def cameras(self) -> tuple[Camera, Camera]:
        """The left and right cameras as calibrated (their first four distortion coefficients)."""
        w, h = self.size

        def camera(k: np.ndarray, d: np.ndarray) -> Camera:
            k1, k2, p1, p2 = (float(v) for v in np.pad(d, (0, 4))[:4])
            return Camera(fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), width=w,
                          height=h, k1=k1, k2=k2, p1=p1, p2=p2)

        return camera(self.k_left, self.d_left), camera(self.k_right, self.d_right)

    @property
    def is_rectified(self) -> bool:
        """Images already rectified: no distortion, identical cameras side by side."""
        t = self.translation / self.baseline_m
        return (not np.any(self.d_left) and not np.any(self.d_right) and np.allclose(self.k_left, self.k_right)
                and np.allclose(self.rotation, np.eye(3), atol=1e-9) and abs(abs(t[0]) - 1.0) < 1e-9)

    def _stereo_rectify(self):
        return cv2.stereoRectify(self.k_left, self.d_left, self.k_right, self.d_right, self.size, self.rotation,
                                 self.translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)

    def rectified(self) -> RectifiedStereo:
        """The pair after rectification (OpenCV stereoRectify, zero disparity at infinity, only
        valid pixels: alpha 0)."""
        r1, _, p1, p2, _, _, _ = self._stereo_rectify()
        w, h = self.size
        camera = Camera(fx=float(p1[0, 0]), fy=float(p1[1, 1]), cx=float(p1[0, 2]), cy=float(p1[1, 2]), width=w,
                        height=h)
        if not np.all(np.isfinite(p1)) or camera.fx <= 0 or camera.fy <= 0:
            raise InputError(f"{self.source}: the calibration gives no usable rectification (focal length "
                             f"{camera.fx:.4g} x {camera.fy:.4g} px after stereoRectify)")
        # stereoRectify's R1 takes raw left-camera vectors into the rectified frame
        return RectifiedStereo(camera, float(-p2[0, 3] / p2[0, 0]), np.asarray(r1, dtype=float).T)

    def rectification_maps(self) -> RectificationMaps:
        """The maps `rectified()`'s pair is made with (fixed-point, for a fast remap)."""
        r1, r2, p1, p2, _, _, _ = self._stereo_rectify()
        maps = [cv2.initUndistortRectifyMap(k, d, r, p, self.size, cv2.CV_16SC2)
                for k, d, r, p in ((self.k_left, self.d_left, r1, p1), (self.k_right, self.d_right, r2, p2))]
        return RectificationMaps(*maps)


# -- OpenCV YAML (FileStorage) -------------------------------------------------------------------

def read_opencv_yaml(path: Path) -> StereoCalibration:
    """OpenCV FileStorage YAML/XML as written by stereoCalibrate samples: K1 (or M1), D1,
    K2 (or M2), D2, R, T, and image_width + image_height (or imageSize)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such calibration file")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise InputError(f"{path}: not an OpenCV FileStorage file (YAML with a %YAML:1.0 header, or XML)")
    try:
        def matrix(names: tuple[str, ...], shape: tuple[int, ...]) -> np.ndarray:
            for name in names:
                node = fs.getNode(name)
                if not node.empty():
                    if node.isReal() or node.isInt():
                        value = np.array([node.real()])
                    elif node.isSeq():
                        value = np.array([node.at(i).real() for i in range(node.size())])
                    else:
                        value = node.mat()
                    if value is None or value.size != int(np.prod(shape)):
                        got = "nothing" if value is None else f"{value.size} values"
                        raise InputError(f"{path}: field '{name}': expected {int(np.prod(shape))} values, got {got}")
                    return value.astype(float).reshape(shape)
            raise InputError(f"{path}: missing field '{' or '.join(names)}'")

        k1, d1 = matrix(("K1", "M1"), (3, 3)), _distortion(path, "D1", fs.getNode("D1"))
        k2, d2 = matrix(("K2", "M2"), (3, 3)), _distortion(path, "D2", fs.getNode("D2"))
        rotation, translation = matrix(("R",), (3, 3)), matrix(("T",), (3,))
        if not fs.getNode("imageSize").empty():
            size = tuple(int(v) for v in matrix(("imageSize",), (2,)))
        else:
            size = (int(matrix(("image_width",), (1,))[0]), int(matrix(("image_height",), (1,))[0]))
    finally:
        fs.release()
    return _checked(StereoCalibration(str(path), k1, d1, k2, d2, size, rotation, translation))


def write_opencv_yaml(path: Path, calibration: StereoCalibration) -> None:
    """A stereo calibration as OpenCV FileStorage YAML (K1 D1 K2 D2 R T, image size), the
    layout `read_opencv_yaml` reads."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise InputError(f"{path}: cannot write the calibration")
    c = calibration
    for name, value in (("K1", c.k_left), ("D1", c.d_left.reshape(1, -1)), ("K2", c.k_right),
                        ("D2", c.d_right.reshape(1, -1)), ("R", c.rotation), ("T", c.translation.reshape(3, 1))):
        fs.write(name, np.asarray(value, dtype=float))
    fs.write("image_width", int(c.size[0]))
    fs.write("image_height", int(c.size[1]))
    fs.release()


def _distortion(path: Path, name: str, node) -> np.ndarray:
    if node.empty():
        raise InputError(f"{path}: missing field '{name}'")
    value = node.mat()
    if value is None or value.size not in (4, 5, 8, 12, 14):
        raise InputError(f"{path}: field '{name}': expected 4, 5, 8, 12 or 14 distortion coefficients")
    return value.astype(float).ravel()


# -- Kalibr camchain ------------------------------------------------------------------------------

def read_kalibr_camchain(path: Path) -> StereoCalibration:
    """cam0 (left) and cam1 (right) of a Kalibr camchain YAML: pinhole cameras with radtan
    distortion; cam1's T_cn_cnm1 takes cam0 points into cam1."""
    data = _yaml(path)
    cams = []
    for name in ("cam0", "cam1"):
        cam = _field(path, data, name, dict)
        model = _field(path, cam, "camera_model", str, name)
        if model not in KALIBR_CAMERA_MODELS:
            raise InputError(f"{path}: {name}.camera_model: '{model}' is not supported "
                             f"(supported: {', '.join(KALIBR_CAMERA_MODELS)}); rectify the images first")
        fu, fv, pu, pv = _numbers(path, cam, "intrinsics", 4, name)
        distortion = _field(path, cam, "distortion_model", str, name) if "distortion_model" in cam else "none"
        if distortion not in KALIBR_DISTORTION_MODELS:
            raise InputError(f"{path}: {name}.distortion_model: '{distortion}' is not supported "
                             f"(supported: {', '.join(KALIBR_DISTORTION_MODELS)})")
        coeffs = _numbers(path, cam, "distortion_coeffs", 4, name) if distortion == "radtan" else np.zeros(4)
        width, height = (int(v) for v in _numbers(path, cam, "resolution", 2, name))
        cams.append((np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1.0]]), coeffs, (width, height)))
    t = _numbers(path, data["cam1"], "T_cn_cnm1", 16, "cam1").reshape(4, 4)
    (k1, d1, size), (k2, d2, _) = cams
    return _checked(StereoCalibration(str(path), k1, d1, k2, d2, size, t[:3, :3], t[:3, 3]))


# -- ROS camera_info ------------------------------------------------------------------------------

def read_camera_info_pair(left: Path, right: Path) -> RectifiedStereo:
    """Two ROS camera_info YAML files of a stereo pair: the rectified model from their
    projection matrices (the right one carries Tx = -fx * baseline)."""
    p_left, size = _camera_info(left)
    p_right, _ = _camera_info(right)
    return rectified_from_projections(p_left, p_right, size, str(right))


def rectified_from_projections(p_left: np.ndarray, p_right: np.ndarray, size: tuple[int, int],
                               right_source: str) -> RectifiedStereo:
    """The rectified model from the two 3x4 projection matrices of a rectified pair (ROS
    camera_info P, KITTI P0/P1): the right one carries Tx = -fx * baseline."""
    if p_right[0, 3] >= 0:
        raise InputError(f"{right_source}: projection matrix Tx = {p_right[0, 3]}: expected -fx * baseline < 0 "
                         "for the right camera (are left and right swapped?)")
    camera = Camera(fx=float(p_left[0, 0]), fy=float(p_left[1, 1]), cx=float(p_left[0, 2]), cy=float(p_left[1, 2]),
                    width=int(size[0]), height=int(size[1]))
    return RectifiedStereo(camera, float((p_left[0, 3] - p_right[0, 3]) / p_right[0, 0]))


def _camera_info(path: Path) -> tuple[np.ndarray, tuple[int, int]]:
    data = _yaml(path)
    width = int(_field(path, data, "image_width", int))
    height = int(_field(path, data, "image_height", int))
    model = data.get("distortion_model", "")
    if model not in ROS_DISTORTION_MODELS:
        raise InputError(f"{path}: distortion_model: '{model}' is not supported "
                         f"(supported: {', '.join(m for m in ROS_DISTORTION_MODELS if m)})")
    projection = _field(path, data, "projection_matrix", dict)
    return _numbers(path, projection, "data", 12, "projection_matrix").reshape(3, 4), (width, height)


# -- shared -------------------------------------------------------------------------------------

def read_stereo_calibration(path: Path, right: Path | None = None) -> RectifiedStereo:
    """Any supported calibration, told apart by content: a Kalibr camchain (cam0/cam1), a pair
    of camera_info files (`right` given), or OpenCV FileStorage YAML/XML; as the rectified pair."""
    raw = read_raw_calibration(path, right)
    return read_camera_info_pair(Path(path), Path(right)) if raw is None else raw.rectified()


def read_raw_calibration(path: Path, right: Path | None = None) -> StereoCalibration | None:
    """The calibration as calibrated (what raw images are rectified with); None for a
    camera_info pair, whose projection matrices describe images that come rectified."""
    path = Path(path)
    if right is not None:
        return None
    text = _read_text(path)
    if text.lstrip().startswith("%YAML") or text.lstrip().startswith("<?xml"):
        return read_opencv_yaml(path)
    if "cam0" in text:
        return read_kalibr_camchain(path)
    raise InputError(f"{path}: not a calibration this reader knows (OpenCV FileStorage with a %YAML:1.0 header, "
                     "Kalibr camchain with cam0/cam1, or a camera_info pair)")


def _read_text(path: Path) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot read calibration: {exc.strerror}") from None


def _yaml(path: Path) -> dict:
    import yaml

    try:
        data = yaml.safe_load(_read_text(path))
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a YAML mapping at the top")
    return data


def _field(path: Path, data: dict, name: str, kind: type, parent: str = ""):
    where = f"{parent}.{name}" if parent else name
    if name not in data:
        raise InputError(f"{path}: missing field '{where}'")
    value = data[name]
    if kind is int and isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, kind):
        raise InputError(f"{path}: field '{where}': expected {kind.__name__}, got {value!r}")
    return value


def _numbers(path: Path, data: dict, name: str, count: int, parent: str) -> np.ndarray:
    value = _field(path, data, name, list, parent)
    flat = np.asarray(value, dtype=object).ravel()
    try:
        array = np.array([float(v) for v in flat])
    except (TypeError, ValueError):
        raise InputError(f"{path}: field '{parent}.{name}': expected {count} numbers") from None
    if array.size != count:
        raise InputError(f"{path}: field '{parent}.{name}': expected {count} numbers, got {array.size}")
    return array


def _checked(calibration: StereoCalibration) -> StereoCalibration:
    c = calibration
    if not np.allclose(c.rotation @ c.rotation.T, np.eye(3), atol=1e-4):
        raise InputError(f"{c.source}: R is not a rotation matrix")
    if c.baseline_m <= 0 or c.k_left[0, 0] <= 0 or c.k_right[0, 0] <= 0:
        raise InputError(f"{c.source}: baseline and focal lengths must be positive")
    return calibration
