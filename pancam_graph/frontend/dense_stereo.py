"""A site panorama's dense local elevation map: OpenCV's semi-global matching (SGBM) on each
rectified WAC pair, the disparities sampled on a grid and triangulated into the body frame.

The orbital DTM it is registered to has 1 m posts, so the pairs are matched at half resolution
(a quarter of the pixels, half the disparity range: about eight times faster, 50 ms a pair);
the grid still puts a point every 2 cm on the near ground, and SGBM's 1/16 px disparity step is
0.6 % of the range at 40 m.

Runs do not use it yet: on rendered sites it registers no better than the image front-end's
tie points and its covariance is too small (docs/orbital.md, "From rendered images"); the
registration study (scripts/orbital_registration_study.py --images) compares the two.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ..errors import FrontendError
from ..rig import Camera, triangulate_rectified, triangulation_covariance

SCALE = 2  # images matched at 1/SCALE resolution
GRID_PX = 6  # a point every GRID_PX pixels (at the matched resolution) in both directions
SIGMA_PX = 1.0  # a disparity's error at full resolution: SGBM's subpixel estimate, half a matched pixel
MIN_RANGE_M = 1.5
CELL_M = 0.5  # the local elevation map's cell: half the orbital DTM's post


def dense_points(left: np.ndarray, right: np.ndarray, camera: Camera, baseline_m: float,
                 max_range_m: float = 40.0) -> np.ndarray:
    """Points (N, 3) in the rectified left camera's frame from one rectified pair, out to
    `max_range_m` along the optical axis."""
    if left.dtype != np.uint8 or right.dtype != np.uint8 or left.ndim != 2 or left.shape != right.shape:
        raise FrontendError(f"dense stereo needs two 8-bit grey images of one size, not {left.dtype} {left.shape} "
                            f"and {right.dtype} {right.shape}")
    small_l, small_r = (cv2.resize(im, None, fx=1 / SCALE, fy=1 / SCALE, interpolation=cv2.INTER_AREA)
                        for im in (left, right))
    focal = camera.fx / SCALE
    least = max(int(np.floor(focal * baseline_m / max_range_m)) - 1, 0)
    span = int(np.ceil((focal * baseline_m / MIN_RANGE_M - least) / 16.0)) * 16
    block = 5
    matcher = cv2.StereoSGBM_create(minDisparity=least, numDisparities=span, blockSize=block,
                                    P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                    uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                    mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disparity = matcher.compute(small_l, small_r).astype(np.float32) / 16.0
    rows, cols = np.mgrid[GRID_PX // 2:disparity.shape[0]:GRID_PX, GRID_PX // 2:disparity.shape[1]:GRID_PX]
    d = disparity[rows, cols]
    valid = d > least
    # back to full-resolution pixels (pixel centres: u_full = SCALE (u + 0.5) - 0.5)
    u = SCALE * (cols[valid] + 0.5) - 0.5
    v = SCALE * (rows[valid] + 0.5) - 0.5
    points = triangulate_rectified(u, u - SCALE * d[valid], v, camera, baseline_m)
    return points[(points[:, 2] > MIN_RANGE_M) & (points[:, 2] <= max_range_m)]


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
