"""A site panorama's dense local elevation map: OpenCV's semi-global matching (SGBM) on each
rectified WAC pair, the disparities sampled on a grid and triangulated into the body frame.

The orbital DTM it is registered to has 1 m posts, so the pairs are matched at half resolution,
which still samples the near ground far finer than the map (docs/performance.md). A site's ground
patch (for the orthoimage) matches the ground within 8 m at a quarter (ground_patch).

Runs do not use it yet: on rendered sites it registers no better than the image front-end's
tie points and its covariance is too small (docs/orbital.md, "From rendered images"); the
registration study (scripts/orbital_registration_study.py --images) compares the two.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FrontendError
from ..geometry.rig import Camera, triangulate_rectified, triangulation_covariance
from ..records import GroundPatch

SCALE = 2  # images matched at 1/SCALE resolution
NEAR_SCALE = 4  # a ground patch's near ground (within NEAR_M) at 1/NEAR_SCALE (_ground_passes)
NEAR_M = 8.0
GRID_PX = 6  # a point every GRID_PX pixels (at the matched resolution) in both directions
SIGMA_PX = 1.0  # a disparity's error at full resolution: SGBM's subpixel estimate, half a matched pixel
MIN_RANGE_M = 1.5
CELL_M = 0.5  # the local elevation map's cell: half the orbital DTM's post
PATCH_CELL_M = 0.25  # the ground patch's cell: half an orthoimage's finest pixel (HiRISE 0.25-0.5 m)


def dense_points(left: np.ndarray, right: np.ndarray, camera: Camera, baseline_m: float,
                 max_range_m: float = 40.0) -> np.ndarray:
    """Points (N, 3) in the rectified left camera's frame from one rectified pair, out to
    `max_range_m` along the optical axis."""
    _check_pair(left, right)
    disparity = _matched(left, right, camera, baseline_m, SCALE, MIN_RANGE_M, max_range_m).disparity
    rows, cols = np.mgrid[GRID_PX // 2:disparity.shape[0]:GRID_PX, GRID_PX // 2:disparity.shape[1]:GRID_PX]
    points = _triangulated(disparity, rows, cols, camera, baseline_m)
    return points[(points[:, 2] > MIN_RANGE_M) & (points[:, 2] <= max_range_m)]


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    if left.dtype != np.uint8 or right.dtype != np.uint8 or left.ndim != 2 or left.shape != right.shape:
        raise FrontendError(f"dense stereo needs two 8-bit grey images of one size, not {left.dtype} {left.shape} "
                            f"and {right.dtype} {right.shape}")


def _sgbm(focal_px: float, baseline_m: float, nearest_m: float, farthest_m: float) -> tuple[int, cv2.StereoSGBM]:
    """The least disparity searched and OpenCV's semi-global matcher for ground from `nearest_m`
    to `farthest_m` at that focal length."""
    least = max(int(np.floor(focal_px * baseline_m / farthest_m)) - 1, 0)
    span = int(np.ceil((focal_px * baseline_m / nearest_m - least) / 16.0)) * 16
    block = 5
    return least, cv2.StereoSGBM_create(minDisparity=least, numDisparities=span, blockSize=block,
                                        P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def _triangulated(disparity: np.ndarray, rows: np.ndarray, cols: np.ndarray, camera: Camera, baseline_m: float,
                  scale: int = SCALE) -> np.ndarray:
    """Points (N, 3), left camera frame, of the pixels (rows, cols) of a disparity image matched
    at 1/scale resolution (_Matched's); NaN rows where it has none."""
    d = disparity[rows, cols]
    # back to full-resolution pixels (pixel centres: u_full = scale (u + 0.5) - 0.5)
    u = scale * (cols + 0.5) - 0.5
    v = scale * (rows + 0.5) - 0.5
    points = triangulate_rectified(u.ravel(), (u - scale * d).ravel(), v.ravel(), camera, baseline_m)
    points[~(d > 0).ravel()] = np.nan  # NaN where SGBM found none (_matched)
    return points


def dense_site_points(views: Sequence, camera: Camera, baseline_m: float, max_range_m: float = 40.0
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """A site's dense points in the body frame (N, 3) and their covariances (N, 3, 3) from its
    rectified views (frontend/panorama.PanoramaView: body_T_camera, left, right); None when no
    pair gives any."""
    points, covariances = [], []
    for view in views:
        p_cam = dense_points(view.left, view.right, camera, baseline_m, max_range_m)
        if not len(p_cam):
            continue
        rotation, shift = view.body_T_camera[:3, :3], view.body_T_camera[:3, 3]
        cov_cam = triangulation_covariance(p_cam, camera, baseline_m, SIGMA_PX)
        points.append(p_cam @ rotation.T + shift)
        covariances.append(rotation @ cov_cam @ rotation.T)
    if not points:
        return None
    return np.vstack(points), np.concatenate(covariances)


def elevation_map(points: np.ndarray, covariances: np.ndarray, cell_m: float = CELL_M
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One point per horizontal cell of the body frame, the one of median height, with its
    covariance: dense stereo puts hundreds of points on a square metre next to the rover and a
    few on one at 40 m, and it is the far relief that places the site on the map."""
    cells = np.floor(points[:, :2] / cell_m).astype(np.int64)
    order = np.lexsort((points[:, 2], cells[:, 1], cells[:, 0]))
    cells = cells[order]
    starts = np.flatnonzero(np.r_[True, np.any(cells[1:] != cells[:-1], axis=1)])
    ends = np.r_[starts[1:], len(order)]
    median = order[(starts + ends) // 2]
    return points[median], covariances[median]


@dataclass(frozen=True)
class _Matched:
    """One pass of SGBM over a pair: its disparities (in its own pixels, NaN where none), the
    left image at its resolution and that resolution's scale."""

    disparity: np.ndarray
    small_left: np.ndarray
    scale: int


def _matched(left: np.ndarray, right: np.ndarray, camera: Camera, baseline_m: float, scale: int, nearest_m: float,
             farthest_m: float, rows: slice = slice(None)) -> _Matched:
    """SGBM over a pair at 1/scale resolution for ground from `nearest_m` to `farthest_m`, on
    `rows` (of that resolution) only."""
    small_l, small_r = (cv2.resize(im, None, fx=1 / scale, fy=1 / scale, interpolation=cv2.INTER_AREA)
                        for im in (left, right))
    least, matcher = _sgbm(camera.fx / scale, baseline_m, nearest_m, farthest_m)
    disparity = np.full(small_l.shape, np.nan, np.float32)
    found = matcher.compute(small_l[rows], small_r[rows]).astype(np.float32) / 16.0
    found[~(found > least)] = np.nan
    disparity[rows] = found
    return _Matched(disparity, small_l, scale)


def _ground_passes(left: np.ndarray, right: np.ndarray, camera: Camera, baseline_m: float, max_range_m: float
                   ) -> list[_Matched]:
    """A pair matched twice for its ground: the whole range at 1/NEAR_SCALE resolution, then at
    1/SCALE only the rows where that found ground beyond NEAR_M, over the disparities of ground
    beyond NEAR_M / 2. Half-resolution SGBM down to 1.5 m was most of a site's ground patch, and
    the near ground's pixels are far finer than a patch cell at either resolution. A far pixel
    is kept where the coarse pass puts it beyond NEAR_M too and within two of its pixels (the
    coarse pass's check on the fine one's narrower search), a near one where the coarse pass
    puts it within NEAR_M. The near pass, then the far one where there is ground beyond NEAR_M."""

    _check_pair(left, right)
    near = _matched(left, right, camera, baseline_m, NEAR_SCALE, MIN_RANGE_M, max_range_m)
    boundary = camera.fx * baseline_m / NEAR_M  # full-resolution disparity of ground at NEAR_M
    near_full = NEAR_SCALE * near.disparity
    passes = [_Matched(np.where(near_full >= boundary, near.disparity, np.nan), near.small_left, NEAR_SCALE)]
    beyond = np.flatnonzero(np.any(near_full < boundary, axis=1))
    if not len(beyond):
        return passes
    ratio, pad = NEAR_SCALE // SCALE, 8  # pad: SGBM's block and its paths near the crop's edge
    far = _matched(left, right, camera, baseline_m, SCALE, NEAR_M / 2, max_range_m,
                   slice(max(beyond[0] * ratio - pad, 0), (beyond[-1] + 1) * ratio + pad))
    coarse = np.repeat(np.repeat(near_full, ratio, axis=0), ratio, axis=1)
    shape = far.disparity.shape
    coarse = np.pad(coarse, ((0, shape[0] - coarse.shape[0]), (0, shape[1] - coarse.shape[1])), constant_values=np.nan)
    agrees = (coarse < boundary) & (np.abs(SCALE * far.disparity - coarse) < 2.0 * NEAR_SCALE)
    return [*passes, _Matched(np.where(agrees, far.disparity, np.nan), far.small_left, SCALE)]


def _on_the_ground(view, matched: _Matched, camera: Camera, baseline_m: float, max_range_m: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """One pass's matched pixels in the body frame (N, 3), and their grey levels, out to
    `max_range_m`."""
    rows, cols = np.nonzero(np.isfinite(matched.disparity))  # the matched pixels only
    p_cam = _triangulated(matched.disparity, rows, cols, camera, baseline_m, matched.scale)
    keep = (p_cam[:, 2] > MIN_RANGE_M) & (p_cam[:, 2] <= max_range_m)
    rotation, shift = view.body_T_camera[:3, :3], view.body_T_camera[:3, 3]
    return p_cam[keep] @ rotation.T + shift, matched.small_left[rows[keep], cols[keep]].astype(np.float64)


def ground_patch(views: Sequence, camera: Camera, baseline_m: float, max_range_m: float = 40.0,
                 cell_m: float = PATCH_CELL_M) -> GroundPatch | None:
    """A site's ground from above: every matched pixel of every rectified pair (_ground_passes:
    at a quarter of the resolution within NEAR_M, at half beyond) put on the ground by its
    disparity, and averaged per `cell_m` cell of the body frame's horizontal grid, as an
    orbiter's pixel averages the ground under it. None when no pair gives any."""
    positions, greys = [], []
    # the next pair matched (OpenCV, without the GIL) while this one is put on the ground (numpy)
    with ThreadPoolExecutor(max_workers=1) as matcher:
        matched = matcher.map(lambda v: _ground_passes(v.left, v.right, camera, baseline_m, max_range_m), views)
        for view, passes in zip(views, matched, strict=True):
            for one in passes:
                placed, grey = _on_the_ground(view, one, camera, baseline_m, max_range_m)
                positions.append(placed)
                greys.append(grey)
    if not positions or not sum(len(p) for p in positions):
        return None
    points, grey = np.vstack(positions), np.concatenate(greys)
    ij = np.floor(points[:, :2] / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    # one integer per cell of the patch's bounding grid (a few hundred thousand): counted by
    # bincount, not sorted by np.unique (a fifth of the patch's time)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    count = np.bincount(key)
    cells = np.flatnonzero(count)
    count = count[cells]
    mean = np.column_stack([np.bincount(key, points[:, k])[cells] for k in range(3)]) / count[:, None]
    return GroundPatch(mean.astype(np.float32), (np.bincount(key, grey)[cells] / count).astype(np.float32),
                       count.astype(np.int32), cell_m)
