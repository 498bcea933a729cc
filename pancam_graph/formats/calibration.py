"""Stereo calibration files: OpenCV YAML, Kalibr camchain, ROS camera_info, MATLAB
stereoParameters (saved as a struct). What they describe is modelled in stereo_pair.py.

Every reader names the file and the field it could not find or understand.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..errors import InputError, ProcessDied
from ..frontend.calibrate import MIN_TARGETS_PER_VIEW, ControlField
from ..geometry.rig import Camera
from ..geometry.stereo_pair import RectifiedStereo, StereoCalibration
from ..runtime.processes import call_apart
from ..runtime.text_files import read_text
from .tables import CsvTable, write_csv

KALIBR_CAMERA_MODELS = ("pinhole",)
KALIBR_DISTORTION_MODELS = ("radtan", "none")  # OpenCV's plumb-bob order (k1, k2, p1, p2)
ROS_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "")


# -- OpenCV YAML (FileStorage) -------------------------------------------------------------------

def read_opencv_yaml(path: Path) -> StereoCalibration:
    """OpenCV FileStorage YAML/XML as written by stereoCalibrate samples: K1 (or M1), D1,
    K2 (or M2), D2, R, T, and image_width + image_height (or imageSize).

    YAML is parsed here, not by OpenCV: OpenCV 5's FileStorage corrupts its heap on some
    malformed matrices (a matrix without `cols` crashed the process later, found by fuzzing)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such calibration file")
    text = read_text(path, "calibration")
    if text.lstrip().startswith("<?xml"):
        nodes = _opencv_xml_nodes(path, text)
    else:
        nodes = _opencv_yaml_nodes(path, text)

    def matrix(names: tuple[str, ...], sizes: tuple[int, ...]) -> np.ndarray:
        for name in names:
            if name in nodes:
                value = _node_values(path, name, nodes[name])
                if value.size not in sizes:
                    raise InputError(f"{path}: field '{name}': expected {' or '.join(map(str, sizes))} values, got "
                                     f"{value.size}")
                return value
        raise InputError(f"{path}: missing field '{' or '.join(names)}'")

    k1, d1 = matrix(("K1", "M1"), (9,)).reshape(3, 3), matrix(("D1",), DISTORTION_SIZES)
    k2, d2 = matrix(("K2", "M2"), (9,)).reshape(3, 3), matrix(("D2",), DISTORTION_SIZES)
    rotation, translation = matrix(("R",), (9,)).reshape(3, 3), matrix(("T",), (3,))
    if "imageSize" in nodes:
        size = matrix(("imageSize",), (2,))
    else:
        size = np.concatenate([matrix(("image_width",), (1,)), matrix(("image_height",), (1,))])
    if not np.all(np.isfinite(size)) or np.any(size != np.round(size)) or np.any(np.abs(size) > 1e6):
        raise InputError(f"{path}: image size {size.tolist()}: expected whole numbers of pixels")
    return _checked(StereoCalibration(str(path), k1, d1, k2, d2, (int(size[0]), int(size[1])), rotation,
                                      translation))


DISTORTION_SIZES = (4, 5, 8, 12, 14)
_OPENCV_SPECIAL = {".nan": float("nan"), ".inf": float("inf"), "+.inf": float("inf"), "-.inf": float("-inf")}


class _OpenCVYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader, with OpenCV's `!!opencv-matrix` read as the mapping it is."""


_OpenCVYamlLoader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                                  lambda loader, node: loader.construct_mapping(node, deep=True))


def _opencv_yaml_nodes(path: Path, text: str) -> dict:
    body = re.sub(r"\A\s*%YAML[: ]?[\d.]*[^\n]*\n", "", text)  # '%YAML:1.0' is OpenCV's, not YAML's
    try:
        data = yaml.load(body, Loader=_OpenCVYamlLoader)  # noqa: S506 - a SafeLoader subclass
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an integer of thousands of digits
        raise InputError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: not an OpenCV FileStorage file (a YAML mapping of K1, D1, K2, D2, R, T)")
    return data


def _opencv_xml_nodes(path: Path, text: str) -> dict:
    """XML FileStorage through OpenCV (rarely used; the YAML form is parsed without it)."""
    for key, value in re.findall(r"<(rows|cols)>\s*(\d+)", text):
        if int(value) > 64:  # OpenCV allocates what the header says before reading the data
            raise InputError(f"{path}: a matrix with {key} = {value}: not a calibration's")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise InputError(f"{path}: not an OpenCV FileStorage file (YAML with a %YAML:1.0 header, or XML)")
        nodes = {}
        for name in ("K1", "M1", "D1", "K2", "M2", "D2", "R", "T", "imageSize", "image_width", "image_height"):
            node = fs.getNode(name)
            if node.empty():
                continue
            if node.isReal() or node.isInt():
                nodes[name] = node.real()
            elif node.isSeq():
                nodes[name] = [node.at(i).real() for i in range(node.size())]
            else:
                value = node.mat()
                nodes[name] = None if value is None else value.ravel().tolist()
        fs.release()
    except (cv2.error, SystemError) as exc:  # FileStorage's parser on a malformed file
        raise InputError(f"{path}: not a valid OpenCV FileStorage file: {str(exc).strip()[-200:]}") from None
    return nodes


def _node_values(path: Path, name: str, node) -> np.ndarray:
    """A FileStorage node's numbers: an opencv-matrix (rows x cols data), a list or a number."""
    if isinstance(node, dict):
        rows, cols, data = node.get("rows"), node.get("cols"), node.get("data")
        if not (isinstance(rows, int) and isinstance(cols, int) and isinstance(data, list)):
            raise InputError(f"{path}: field '{name}': an opencv-matrix needs rows, cols and data")
        if len(data) != rows * cols:
            raise InputError(f"{path}: field '{name}': {len(data)} values for {rows} x {cols}")
        node = data
    values = node if isinstance(node, list) else [node]
    # OpenCV writes .Nan and .Inf, which YAML 1.1 reads as text
    values = [_OPENCV_SPECIAL.get(v.lower(), v) if isinstance(v, str) else v for v in values]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise InputError(f"{path}: field '{name}': expected numbers, got {node!r:.80}")
    try:
        return np.array(values, dtype=float)
    except OverflowError:
        raise InputError(f"{path}: field '{name}': a number beyond floating point") from None


def write_opencv_yaml(path: Path, calibration: StereoCalibration, rectification: bool = False) -> None:
    """A stereo calibration as OpenCV FileStorage YAML (K1 D1 K2 D2 R T, image size), the
    layout `read_opencv_yaml` reads; with `rectification`, also stereoRectify's R1 R2 P1 P2 Q
    as OpenCV's stereo_calib sample writes them (readers recompute them from the rest)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise InputError(f"{path}: cannot write the calibration")
    c = calibration
    fields = [("K1", c.k_left), ("D1", c.d_left.reshape(1, -1)), ("K2", c.k_right), ("D2", c.d_right.reshape(1, -1)),
              ("R", c.rotation), ("T", c.translation.reshape(3, 1))]
    if rectification:
        fields += list(zip(("R1", "R2", "P1", "P2", "Q"), c.stereo_rectify()[:5], strict=True))
    for name, value in fields:
        fs.write(name, np.asarray(value, dtype=float))
    fs.write("image_width", int(c.size[0]))
    fs.write("image_height", int(c.size[1]))
    fs.release()


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


# -- MATLAB stereoParameters ----------------------------------------------------------------------

MATLAB_UNITS_M = {"mm": 1e-3, "millimeters": 1e-3, "cm": 1e-2, "centimeters": 1e-2, "m": 1.0, "meters": 1.0}


def read_matlab_stereo_parameters(path: Path, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """A MATLAB stereoParameters object saved as a struct (`struct(stereoParams)`, its two
    CameraParameters too, as the ESA Katwijk data set's calibrations are): read with scipy.

    MATLAB's conventions are not OpenCV's: IntrinsicMatrix is K transposed and its pixels are
    1-based; RotationOfCamera2 multiplies row vectors (OpenCV's R is its transpose);
    TranslationOfCamera2 is in the calibration's WorldUnits. `image_size` (width, height) is
    needed when the file's ImageSize is empty, as older MATLAB releases leave it."""
    path = Path(path)
    try:
        # scipy's reader can die of a segfault on a damaged file (tests/data/fuzz/README.md): read
        # apart, so that a bad file costs a child process and not the run.
        return call_apart(_read_matlab_stereo_parameters, path, image_size)
    except ProcessDied:
        raise InputError(f"{path}: reading it crashed scipy's MATLAB reader (the file is damaged, or not a "
                         "MATLAB .mat file); a stereoParameters object must be saved as a struct (v7 or "
                         "earlier, not v7.3)") from None


def _read_matlab_stereo_parameters(path: Path, image_size: tuple[int, int] | None) -> StereoCalibration:
    import scipy.io

    try:
        data = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except Exception as exc:  # scipy raises assorted errors (IndexError, ValueError, ...) on a malformed file
        raise InputError(f"{path}: not a MATLAB .mat file scipy can read ({exc}); a stereoParameters object "
                         "must be saved as a struct (v7 or earlier, not v7.3)") from None
    params = {k: v for k, v in data.items() if not k.startswith("__") and hasattr(v, "CameraParameters1")}
    if len(params) > 1:
        params.pop("ans", None)  # MATLAB's last answer, saved along when the whole workspace was
    if len(params) != 1:
        raise InputError(f"{path}: expected one stereoParameters struct (with CameraParameters1/2), found "
                         f"{len(params)} ({', '.join(params)}); MATLAB objects must be converted with struct() "
                         "before saving")
    stereo = next(iter(params.values()))

    def numbers(obj, name: str, size: int | None, parent: str) -> np.ndarray:
        value = getattr(obj, name, None)
        try:
            array = np.asarray(value, dtype=float).ravel()
        except (TypeError, ValueError):
            array = np.zeros(0)
        if value is None or (size is not None and array.size != size) or not np.all(np.isfinite(array)):
            expected = f"{size} finite numbers" if size else "finite numbers"
            raise InputError(f"{path}: field '{parent}{name}': expected {expected}, got {value!r:.60}")
        return array

    scale = MATLAB_UNITS_M.get(str(getattr(stereo, "WorldUnits", "")).strip().lower())
    if scale is None:
        raise InputError(f"{path}: field 'WorldUnits': {getattr(stereo, 'WorldUnits', None)!r} is not a length "
                         f"unit this reader knows ({', '.join(sorted(MATLAB_UNITS_M))})")
    cameras, sizes = [], []
    for name in ("CameraParameters1", "CameraParameters2"):
        cam = getattr(stereo, name)
        k = numbers(cam, "IntrinsicMatrix", 9, f"{name}.").reshape(3, 3).T
        k[:2, 2] -= 1.0  # MATLAB's first pixel centre is (1, 1), OpenCV's (0, 0)
        radial = numbers(cam, "RadialDistortion", None, f"{name}.")
        tangential = numbers(cam, "TangentialDistortion", 2, f"{name}.")
        if radial.size not in (2, 3):
            raise InputError(f"{path}: field '{name}.RadialDistortion': expected 2 or 3 coefficients")
        d = np.array([radial[0], radial[1], tangential[0], tangential[1], radial[2] if radial.size == 3 else 0.0])
        size = np.asarray(getattr(cam, "ImageSize", []), dtype=float).ravel()
        sizes.append(None if size.size == 0 else (int(size[1]), int(size[0])))  # MATLAB: [rows, columns]
        cameras.append((k, d, np.asarray(getattr(cam, "ReprojectedPoints", np.zeros((0, 2, 1))), dtype=float)))
    size = image_size or sizes[0]
    if size is None:
        reached = np.concatenate([c[2].reshape(-1, 2, *c[2].shape[2:]).swapaxes(1, -1).reshape(-1, 2)
                                  for c in cameras if c[2].size])
        hint = (f"; its calibration points reach x = {reached[:, 0].max():.0f}, y = {reached[:, 1].max():.0f} px"
                if len(reached) else "")
        raise InputError(f"{path}: CameraParameters1.ImageSize is empty (older MATLAB releases leave it so): give "
                         f"the image size (width, height){hint}")
    rotation = numbers(stereo, "RotationOfCamera2", 9, "").reshape(3, 3).T
    translation = numbers(stereo, "TranslationOfCamera2", 3, "") * scale
    (k1, d1, _), (k2, d2, _) = cameras
    return _checked(StereoCalibration(str(path), k1, d1, k2, d2, (int(size[0]), int(size[1])), rotation,
                                      translation))


# -- ROS camera_info ------------------------------------------------------------------------------

def read_camera_info_pair(left: Path, right: Path) -> RectifiedStereo:
    """Two ROS camera_info YAML files of a stereo pair: the rectified model from their
    projection matrices (the right one carries Tx = -fx * baseline)."""
    p_left, size = _camera_info(left)
    p_right, _ = _camera_info(right)
    return rectified_from_projections(p_left, p_right, size, (str(left), str(right)))


def rectified_from_projections(p_left: np.ndarray, p_right: np.ndarray, size: tuple[int, int],
                               sources: tuple[str, str]) -> RectifiedStereo:
    """The rectified model from the two 3x4 projection matrices of a rectified pair (ROS
    camera_info P, KITTI P0/P1): the right one carries Tx = -fx * baseline. `sources` name
    where the left and the right matrix came from, for messages."""
    left_source, right_source = sources
    for source, projection in zip(sources, (p_left, p_right), strict=True):
        if not np.all(np.isfinite(projection)):
            raise InputError(f"{source}: the projection matrix has a value that is not a finite number")
    _check_intrinsics(left_source, "left", p_left[0, 0], p_left[1, 1], p_left[0, 2], p_left[1, 2], *size)
    _check_intrinsics(right_source, "right", p_right[0, 0], p_right[1, 1], p_right[0, 2], p_right[1, 2], *size)
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

def read_stereo_calibration(path: Path, right: Path | None = None, image_size: tuple[int, int] | None = None
                            ) -> tuple[StereoCalibration | None, RectifiedStereo]:
    """Any supported calibration, told apart by content: a Kalibr camchain (cam0/cam1), a pair
    of camera_info files (`right` given), OpenCV FileStorage YAML/XML, or a MATLAB .mat. Returns
    it as calibrated (None for a camera_info pair, whose images come rectified) and as the
    rectified pair."""
    raw = read_raw_calibration(path, right, image_size)
    return raw, (read_camera_info_pair(Path(path), Path(right)) if raw is None else raw.rectified())


def read_raw_calibration(path: Path, right: Path | None = None,
                         image_size: tuple[int, int] | None = None) -> StereoCalibration | None:
    """The calibration as calibrated (what raw images are rectified with); None for a
    camera_info pair, whose projection matrices describe images that come rectified.
    `image_size` (width, height): for a MATLAB file that does not record it."""
    path = Path(path)
    if right is not None:
        return None
    if path.suffix.lower() == ".mat":
        return read_matlab_stereo_parameters(path, image_size)
    text = read_text(path, "calibration")
    if text.lstrip().startswith("%YAML") or text.lstrip().startswith("<?xml"):
        return read_opencv_yaml(path)
    if "cam0" in text:
        return read_kalibr_camchain(path)
    raise InputError(f"{path}: not a calibration this reader knows (OpenCV FileStorage with a %YAML:1.0 header, "
                     "Kalibr camchain with cam0/cam1, MATLAB stereoParameters .mat, or a camera_info pair)")


def _yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(read_text(path, "calibration"))
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an integer of thousands of digits
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
    """A calibration VO can use: finite numbers, a proper rotation, positive focal lengths and
    baseline, principal points on the image (a broken one would fail VO at every stop and the
    run would quietly be dead reckoning)."""
    c = calibration
    for name, value in (("K1", c.k_left), ("D1", c.d_left), ("K2", c.k_right), ("D2", c.d_right),
                        ("R", c.rotation), ("T", c.translation)):
        if not np.all(np.isfinite(value)):
            raise InputError(f"{c.source}: {name} has a value that is not a finite number: {value.ravel().tolist()}")
    if not np.allclose(c.rotation @ c.rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(c.rotation) < 0:
        raise InputError(f"{c.source}: R is not a rotation matrix")
    width, height = c.size
    if width <= 0 or height <= 0:
        raise InputError(f"{c.source}: image size {width} x {height} px must be positive")
    for name, k in (("left", c.k_left), ("right", c.k_right)):
        _check_intrinsics(c.source, name, k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
    if c.baseline_m <= 1e-4:
        raise InputError(f"{c.source}: baseline {c.baseline_m:.3g} m: expected a stereo pair's (positive)")
    return calibration


def _check_intrinsics(source: str, camera: str, fx: float, fy: float, cx: float, cy: float, width: int,
                      height: int) -> None:
    if not (fx > 0 and fy > 0):
        raise InputError(f"{source}: {camera} camera focal lengths fx = {fx:.6g}, fy = {fy:.6g} px must be positive")
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise InputError(f"{source}: {camera} camera principal point ({cx:.6g}, {cy:.6g}) px is off the "
                         f"{width} x {height} image")


# -- control field (calibrate) ----------------------------------------------------------------------

CONTROL_FIELD_COLUMNS = ["target_id", "panel", "x_m", "y_m", "z_m"]


def write_control_field(path: Path, field: ControlField) -> None:
    """The field's surveyed targets (marker centres), one row each, metres."""
    write_csv(path, CONTROL_FIELD_COLUMNS, [[int(t), int(p), *(f"{v:.6f}" for v in xyz)]
                                            for t, p, xyz in zip(field.ids, field.panel, field.points, strict=True)])


def read_control_field(path: Path) -> ControlField:
    """A control field CSV (`write_control_field`'s columns): each target once, ids of the
    ArUco 4x4 dictionary (0-249), finite coordinates in metres, a panel number per flat surface."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such control field file (columns {','.join(CONTROL_FIELD_COLUMNS)})")
    table = CsvTable(path, CONTROL_FIELD_COLUMNS)
    points: dict[int, np.ndarray] = {}
    panels: dict[int, int] = {}
    for line, row in table.rows:
        values = table.values(line, row)
        target, panel = (int(table.number(line, c, v, integer=True))
                         for c, v in zip(CONTROL_FIELD_COLUMNS[:2], values[:2], strict=True))
        if not 0 <= target < 250:
            raise InputError(f"{path}: line {line}: target_id {target} is not an ArUco 4x4 id (0-249)")
        if target in points:
            raise InputError(f"{path}: line {line}: target {target} given twice")
        if not 0 <= panel < 250:
            raise InputError(f"{path}: line {line}: panel {panel} outside 0-249")
        xyz = np.array([table.number(line, c, v) for c, v in zip(CONTROL_FIELD_COLUMNS[2:], values[2:], strict=True)])
        if np.any(np.abs(xyz) > 1e4):
            raise InputError(f"{path}: line {line}: a coordinate beyond 10 km")
        points[target], panels[target] = xyz, panel
    if len(points) < MIN_TARGETS_PER_VIEW:
        raise InputError(f"{path}: {len(points)} targets; calibration needs at least {MIN_TARGETS_PER_VIEW}")
    ids = np.array(sorted(points))
    return ControlField(ids, np.array([points[t] for t in ids]), np.array([panels[t] for t in ids]))
