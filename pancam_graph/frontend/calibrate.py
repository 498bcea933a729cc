"""Stereo calibration from images of a 3-D control field (the dissertation's section 4.2): coded square
targets at surveyed positions on surfaces at several depths, seen by both cameras from several
views. Each camera is calibrated on its own (focal lengths, principal point, k1, k2, p1, p2),
then the pair's boresight (R, T) with the intrinsics held, as OpenCV's stereoCalibrate does.

A target is a square coded marker (ArUco); its point is the marker's centre, found in the image
as the crossing of the detected quadrilateral's diagonals. The corners themselves are biased:
sub-pixel refinement of a blurred outer corner pulls it about 0.25 px inwards along the
diagonal, which the crossing cancels (0.09 px RMS against the renderer's truth, against 0.26 px
for the corners).

A planar board alone ties focal length to distance; the field's depth separates them, which
is why OpenCV needs a first guess for a non-planar target: it comes from the field's largest
flat panel in each view (Zhang's method on that panel alone).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError
from ..geometry.stereo_pair import StereoCalibration

ARUCO_DICTIONARY = cv2.aruco.DICT_4X4_250
MIN_TARGETS_PER_VIEW = 12  # fewer and a view's pose is weak (and a stray detection weighs)
OUTLIER_PX = 1.0  # a corner this far from the first fit is a misdetection, not noise


@dataclass(frozen=True)
class ControlField:
    """Square coded targets (ArUco 4x4, ids 0-249) at surveyed positions: `points[i]` is target
    `ids[i]`'s centre in the field frame (m); `panel[i]` names the flat surface it is on
    (targets on one panel are coplanar: the first guess uses the largest)."""

    ids: np.ndarray  # (N,) int
    points: np.ndarray  # (N, 3) m
    panel: np.ndarray  # (N,) int

    def __post_init__(self):
        if len(set(self.ids.tolist())) != len(self.ids):
            raise InputError("control field: a target id appears twice")

    def lookup(self) -> dict[int, int]:
        return {int(t): i for i, t in enumerate(self.ids)}


@dataclass
class Detections:
    """One image's targets: ids (M,) and their centres (M, 2) px."""

    ids: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class CameraFit:
    """One camera's calibration: K, D (k1, k2, p1, p2), the RMS reprojection error (px) over
    the targets kept, how many were kept and dropped, and the 1-sigma uncertainty of fx, fy,
    cx, cy, k1, k2, p1, p2."""

    k: np.ndarray
    d: np.ndarray
    rms_px: float
    targets: int
    rejected: int
    sigma: np.ndarray


@dataclass
class StereoFit:
    """The pair: both cameras, the boresight and its RMS over the targets both saw."""

    calibration: StereoCalibration
    left: CameraFit
    right: CameraFit
    stereo_rms_px: float
    views: int


def detect_targets(image: np.ndarray, field: ControlField) -> Detections:
    """The field's targets in one 8-bit grey image: each marker's centre from its sub-pixel
    corners; ids the field does not have are dropped (another board in view)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 4
    params.cornerRefinementMinAccuracy = 0.001
    params.cornerRefinementMaxIterations = 100
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY), params)
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return Detections(np.zeros(0, dtype=int), np.zeros((0, 2)))
    known = field.lookup()
    keep = [i for i, t in enumerate(ids.ravel()) if int(t) in known]
    return Detections(ids.ravel()[keep].astype(int),
                      np.array([_centre(corners[i].reshape(4, 2)) for i in keep]).reshape(-1, 2))


def _centre(quad: np.ndarray) -> np.ndarray:
    """Where the diagonals of a quadrilateral (4, 2) cross: the image of the square's centre
    under any homography."""
    h = np.column_stack([quad, np.ones(4)])
    x = np.cross(np.cross(h[0], h[2]), np.cross(h[1], h[3]))
    return x[:2] / x[2]


def calibrate_stereo(field: ControlField, left: list[Detections], right: list[Detections],
                     size: tuple[int, int], names: list[str] | None = None) -> StereoFit:
    """Calibrate each camera, then the pair, from the targets found in each view's two images."""
    names = names or [f"view {i}" for i in range(len(left))]
    usable = [i for i in range(len(left)) if min(len(left[i]), len(right[i])) >= MIN_TARGETS_PER_VIEW]
    if len(usable) < 3:
        seen = ", ".join(f"{names[i]}: {len(left[i])}/{len(right[i])}" for i in range(len(left)))
        raise InputError(f"calibration needs at least 3 views with {MIN_TARGETS_PER_VIEW} or more targets in both "
                         f"images; targets found (left/right): {seen or 'no views'}")
    try:
        return _calibrate_pair(field, left, right, size, usable)
    except cv2.error as exc:  # a degenerate set of views (all targets on one line, ...)
        message = str(exc).strip().splitlines()[-1]
        raise InputError(f"calibration: OpenCV could not fit these views ({message})") from None


def _calibrate_pair(field: ControlField, left: list[Detections], right: list[Detections], size: tuple[int, int],
                    usable: list[int]) -> StereoFit:
    left_fit, left_kept = _calibrate_camera(field, [left[i] for i in usable], size)
    right_fit, right_kept = _calibrate_camera(field, [right[i] for i in usable], size)

    # The boresight from the targets kept in both images of a view.
    lookup = field.lookup()
    obj, img_l, img_r = [], [], []
    for v, i in enumerate(usable):
        both = sorted(left_kept[v] & right_kept[v])
        if len(both) < MIN_TARGETS_PER_VIEW:
            continue
        where_l = {int(t): j for j, t in enumerate(left[i].ids)}
        where_r = {int(t): j for j, t in enumerate(right[i].ids)}
        obj.append(field.points[[lookup[t] for t in both]].astype(np.float32))
        img_l.append(left[i].points[[where_l[t] for t in both]].astype(np.float32))
        img_r.append(right[i].points[[where_r[t] for t in both]].astype(np.float32))
    if len(obj) < 3:
        raise InputError("calibration: fewer than 3 views share enough targets between the left and right images")
    rms, k1, d1, k2, d2, rotation, translation, _, _ = cv2.stereoCalibrate(
        obj, img_l, img_r, left_fit.k, left_fit.d, right_fit.k, right_fit.d, size, flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    calibration = StereoCalibration("calibrate", k1, d1.ravel(), k2, d2.ravel(), (int(size[0]), int(size[1])),
                                    rotation, translation.ravel())
    return StereoFit(calibration, left_fit, right_fit, float(rms), len(obj))


def _calibrate_camera(field: ControlField, views: list[Detections], size: tuple[int, int]
                      ) -> tuple[CameraFit, list[set[int]]]:
    """One camera: a first guess from the largest panel, then every target in 3-D; targets more
    than OUTLIER_PX off the fit are dropped and the fit repeated. Returns the fit and, per
    view, the ids kept."""
    lookup = field.lookup()
    flags = cv2.CALIB_FIX_K3
    # Zhang's method on the largest panel's targets (coplanar: no guess needed).
    biggest = np.bincount(field.panel).argmax()
    flat = [np.array([field.panel[lookup[int(t)]] == biggest for t in det.ids], dtype=bool) for det in views]
    flat_views = [(det, f) for det, f in zip(views, flat, strict=True) if f.sum() >= 6]
    if len(flat_views) < 2:
        raise InputError("calibration: the field's largest panel is seen with 6 or more targets in fewer than 2 "
                         "views")
    _, k0, d0, _, _ = cv2.calibrateCamera(
        [field.points[[lookup[int(t)] for t in det.ids[f]]].astype(np.float32) for det, f in flat_views],
        [det.points[f].astype(np.float32) for det, f in flat_views], size, None, None, flags=flags)

    kept = [np.ones(len(det), dtype=bool) for det in views]
    rejected = 0
    for fit in range(3):
        obj = [field.points[[lookup[int(t)] for t in det.ids[keep]]].astype(np.float32)
               for det, keep in zip(views, kept, strict=True)]
        img = [det.points[keep].astype(np.float32) for det, keep in zip(views, kept, strict=True)]
        rms, k, d, rvecs, tvecs, sigma = cv2.calibrateCameraExtended(
            obj, img, size, k0.copy(), d0.copy(), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))[:6]
        if fit == 2:
            break
        dropped = 0
        for v, (det, keep, r, t) in enumerate(zip(views, kept, rvecs, tvecs, strict=True)):
            all_obj = field.points[[lookup[int(x)] for x in det.ids]]
            error = np.linalg.norm(cv2.projectPoints(all_obj, r, t, k, d)[0].reshape(-1, 2) - det.points, axis=1)
            kept[v] = keep & (error <= OUTLIER_PX)
            dropped += int(keep.sum() - kept[v].sum())
        if dropped == 0:
            break
        rejected, k0, d0 = rejected + dropped, k, d
    return (CameraFit(k, d.ravel()[:4], float(rms), int(sum(keep.sum() for keep in kept)), rejected,
                      sigma.ravel()[:8]),
            [{int(t) for t in det.ids[keep]} for det, keep in zip(views, kept, strict=True)])
