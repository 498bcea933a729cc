"""A site's local elevation map registered to an orbital DTM: where the map puts the rover.

The site's triangulated points (its panorama's stereo, in the body frame) are a sparse local
elevation map; registering it is DEM-to-DEM co-registration on heights (the objective of Nuth &
Kääb's method): find the shift east, north and up and the turn about the vertical of the
predicted pose that make the points' heights agree with the DTM's. A coarse search over
horizontal shifts covers the prediction's uncertainty; SciPy's robust least squares (soft L1)
refines the four; the covariance is the least-squares sandwich (register_site).
The result is the rover's position and heading in the map's frame (local ENU as the map states
it).

Why not ICP: small_gicp's GICP estimates each point's covariance from its neighbours, which on
sparse, noisy tie points is noise, and its Python binding takes no covariance of ours: on a
simulated crater field its errors were bimodal (3 cm, or 0.7-0.9 m and 1.6-3.1 deg) with a
mean NEES of 33 for 3 dof; its point-to-plane factor was off by 0.23 m (median) even on
noise-free points. A height field is registered best on heights.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pyproj import CRS

from ..errors import PancamGraphError
from ..geometry.geodesy import LocalFrame
from ..records import MapRaster
from .maps import ground_spacing

MAX_POINTS = 4000  # a site's points used at most (a simulated panorama has 2,000-2,600 within 40 m)
_DISTINCT_M = 2.0  # a place this far from the best one is another place, not the same one less well fitted


class RegistrationFailed(PancamGraphError):
    """A site that cannot be registered to a map (the reason is the message)."""


class MapNotCovering(RegistrationFailed):
    """The map does not reach round the site."""


@dataclass(frozen=True)
class Registration:
    """The rover's pose in the map's frame at a site, from its points against the map's DTM."""

    map_T_body: np.ndarray  # 4x4, local ENU as the map has it
    covariance: np.ndarray  # (4, 4) of east, north, up (m) and yaw (rad)
    seconds: float

    @property
    def measurement(self) -> np.ndarray:
        """(east, north, up, yaw) of the body in the map's frame."""
        return np.array([*self.map_T_body[:3, 3], yaw_of(self.map_T_body[:3, :3])])


def yaw_of(rotation: np.ndarray) -> float:
    """Heading of the body's forward (x) axis, anticlockwise from east."""
    return float(np.arctan2(rotation[1, 0], rotation[0, 0]))


def yaw_jacobian(rotation: np.ndarray) -> np.ndarray:
    """(3,) derivative of yaw_of(R exp(w)) in w at 0 (GTSAM's right perturbation of a Pose3)."""
    f = rotation[:, 0]
    d_yaw_d_f = np.array([-f[1], f[0], 0.0]) / (f[0] ** 2 + f[1] ** 2)
    e_x_cross = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return d_yaw_d_f @ (-rotation @ e_x_cross)


@dataclass(frozen=True)
class DtmErrors:
    """What the registration assumes of the errors: the ground a point lies on against the DTM's
    smooth surface (rocks, the DTM's resolution), independent per point; and the DTM's own height
    error, shared by points closer than its correlation length (an orbital DTM's error is smooth:
    its stereo matching windows span several posts)."""

    surface_sigma_m: float = 0.25
    dtm_sigma_m: float = 0.1
    dtm_correlation_m: float = 3.0


def register_site(points_body: np.ndarray, vertical_var_body: np.ndarray, predicted_map_T_body: np.ndarray,
                  dtm: MapRaster, frame: LocalFrame, search_m: float, errors: DtmErrors = DtmErrors(),
                  max_range_m: float = 25.0, min_points: int = 30, min_distinctness: float = 50.0) -> Registration:
    """Register a site's points (N, 3, body frame; each with the variance of its height in the
    world, (N,)) to `dtm`, starting from the predicted pose in the map's frame and searching
    `search_m` about it horizontally. Raises RegistrationFailed with the reason when too few
    points, a map that does not cover the site or a hole in it leave nothing to trust, or when
    the site's relief fits another place within the search nearly as well: the best place more
    than 2 m away must fit worse by `min_distinctness` (summed squared weighted residuals). The
    fit's covariance describes the one minimum it is in; it cannot say that another was as good.

    The covariance is the least-squares sandwich (J'J)^-1 J' C J (J'J)^-1 with C the weighted
    residuals' covariance: the independent part at the fit's residual variance, plus the DTM's
    correlated error, which no number of points averages away."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.optimize import least_squares

    start = time.perf_counter()
    near = np.flatnonzero(np.hypot(points_body[:, 0], points_body[:, 1]) <= max_range_m)
    if len(near) > MAX_POINTS:  # an image front-end's dense tracks: every k-th, spread over the site
        near = near[np.linspace(0, len(near) - 1, MAX_POINTS).astype(int)]
    points_body, variance = points_body[near], vertical_var_body[near]
    if len(points_body) < min_points:
        raise RegistrationFailed(f"{len(points_body)} site points within {max_range_m:g} m, fewer than {min_points}")
    crs = CRS.from_wkt(dtm.crs_wkt)
    site_enu = predicted_map_T_body[:3, 3]
    # ENU -> map is affine over a site (to 1e-7 across 50 m); the height above the body's surface
    # differs from ENU up by the curvature's drop, which a shift of metres changes by millimetres
    ends = frame.to_map(np.array([site_enu, site_enu + [1.0, 0.0, 0.0], site_enu + [0.0, 1.0, 0.0]]), crs)
    site_xy, to_map = ends[0], (ends[1:] - ends[0]).T
    rows, cols = _window(dtm, site_xy, max_range_m + search_m + 2 * max(ground_spacing(dtm)))
    window = dtm.values[rows, cols].astype(float)
    if np.isnan(window).mean() > 0.05:
        raise RegistrationFailed(f"the map has no data at {np.isnan(window).mean():.0%} of the site's posts")
    x, y = dtm.centres()
    surface = RegularGridInterpolator((y[rows][::-1], x[cols]), window[::-1], bounds_error=False, fill_value=np.nan)
    predicted = points_body @ predicted_map_T_body[:3, :3].T + site_enu
    drop = frame.to_geodetic(predicted)[:, 2] - predicted[:, 2]
    weight = 1.0 / np.sqrt(variance + errors.surface_sigma_m**2)

    def moved(p: np.ndarray) -> np.ndarray:
        """The points with the body shifted by (east, north, up) and turned by yaw about itself."""
        c, s = np.cos(p[2]), np.sin(p[2])
        arm = predicted[:, :2] - site_enu[:2]
        xy = site_enu[:2] + p[:2] + arm @ np.array([[c, s], [-s, c]])
        return np.column_stack([xy, predicted[:, 2] + p[3]])

    def residuals(p: np.ndarray) -> np.ndarray:
        at = moved(p)
        map_xy = site_xy + (at[:, :2] - site_enu[:2]) @ to_map.T
        r = weight * (at[:, 2] + drop - surface(map_xy[:, ::-1]))
        return np.nan_to_num(r, nan=10.0)  # a point off the window: a gross residual

    base_xy = site_xy + (predicted[:, :2] - site_enu[:2]) @ to_map.T
    pixel = np.column_stack([(y[rows][0] - base_xy[:, 1]) / dtm.post_m, (base_xy[:, 0] - x[cols][0]) / dtm.post_m])
    shift, margin = _coarse_shift(window, pixel, predicted[:, 2] + drop, weight, to_map / dtm.post_m, search_m)
    if margin < min_distinctness:
        raise RegistrationFailed(f"the site's relief is ambiguous: another place within {search_m:.1f} m fits nearly "
                                 f"as well ({margin:.0f} worse, {min_distinctness:g} needed)")
    fit = least_squares(residuals, np.array([*shift, 0.0, _vertical(residuals, shift)]), loss="soft_l1",
                        f_scale=2.0, x_scale=[1.0, 1.0, 0.01, 1.0], method="trf")
    r = fit.fun
    inliers = np.abs(r) < 3.0
    if inliers.sum() < min_points:
        raise RegistrationFailed(f"{int(inliers.sum())} of {len(r)} site points agree with the map")
    jacobian = fit.jac[inliers]
    sigma2 = float(np.sum(r[inliers] ** 2) / max(inliers.sum() - 4, 1))
    try:
        normal_inverse = np.linalg.inv(jacobian.T @ jacobian)
    except np.linalg.LinAlgError:
        raise RegistrationFailed("the site's relief leaves the fit undetermined (singular normal matrix)") from None
    spread = _shared_error_spread(moved(fit.x)[inliers, :2], weight[inliers, None] * jacobian, errors)
    covariance = sigma2 * normal_inverse + normal_inverse @ spread @ normal_inverse
    pose = predicted_map_T_body.copy()
    c, s = np.cos(fit.x[2]), np.sin(fit.x[2])
    pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose[:3, :3]
    pose[:3, 3] += [fit.x[0], fit.x[1], fit.x[3]]
    order = [0, 1, 3, 2]  # the fit's (east, north, yaw, up) as (east, north, up, yaw)
    return Registration(pose, covariance[np.ix_(order, order)], time.perf_counter() - start)


def _shared_error_spread(xy: np.ndarray, weighted_jacobian: np.ndarray, errors: DtmErrors) -> np.ndarray:
    """J' C J of the DTM's shared error: C_ij = dtm_sigma^2 exp(-d_ij^2 / 2 l^2) w_i w_j over the
    points' horizontal distances d_ij (the weights already in `weighted_jacobian`, rows w_i J_i).
    Pairs beyond 4 l (a correlation below 3e-4) are left out: a site's points have a few hundred
    neighbours within that, not thousands."""
    from scipy.spatial import cKDTree

    a = weighted_jacobian
    length = errors.dtm_correlation_m
    pairs = cKDTree(xy).query_pairs(4.0 * length, output_type="ndarray")
    shared = a.T @ a
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        k = np.exp(-np.sum((xy[i] - xy[j]) ** 2, axis=1) / (2.0 * length**2))
        cross = (a[i] * k[:, None]).T @ a[j]
        shared += cross + cross.T
    return errors.dtm_sigma_m**2 * shared


def _window(dtm: MapRaster, centre_xy: np.ndarray, radius_m: float) -> tuple[slice, slice]:
    """The raster's rows and columns within `radius_m` on the ground of a map point (the posts'
    ground spacing per axis: maps.ground_spacing); MapNotCovering when that box reaches outside
    the raster."""
    east_m, north_m = ground_spacing(dtm)
    half_cols, half_rows = radius_m / east_m * dtm.post_m, radius_m / north_m * dtm.post_m  # map units
    col0 = int(np.floor((centre_xy[0] - half_cols - dtm.x0_m) / dtm.post_m))
    row0 = int(np.floor((dtm.y0_m - centre_xy[1] - half_rows) / dtm.post_m))
    cols = int(np.ceil(2 * half_cols / dtm.post_m)) + 1
    rows = int(np.ceil(2 * half_rows / dtm.post_m)) + 1
    height, width = dtm.values.shape
    if row0 < 0 or col0 < 0 or row0 + rows > height or col0 + cols > width:
        raise MapNotCovering(f"the site is not covered by the map (within {radius_m:.0f} m of its predicted "
                             "position)")
    return slice(row0, row0 + rows), slice(col0, col0 + cols)


def _coarse_shift(window: np.ndarray, pixel: np.ndarray, heights: np.ndarray, weight: np.ndarray,
                  enu_to_pixel: np.ndarray, search_m: float, step_m: float = 0.5) -> tuple[np.ndarray, float]:
    """The horizontal shift (east, north) within search_m of the prediction whose heights agree
    best with the DTM's (`window`, the points at (row, col) `pixel`), a vertical offset aside:
    the smallest sum of clipped squared weighted residuals. And by how much the best shift more
    than `_DISTINCT_M` away does worse: the site's relief tells its place from every other
    within the search by that much."""
    from scipy.ndimage import map_coordinates

    offsets = np.arange(-search_m, search_m + step_m / 2, step_m)
    grid = np.array([(dx, dy) for dx in offsets for dy in offsets])
    moved_px = grid @ enu_to_pixel.T  # map (x, y) per ENU shift, in pixels: rows run south
    costs = np.empty(len(grid))
    chunk = max(1, 2_000_000 // len(pixel))
    for start in range(0, len(grid), chunk):
        d = moved_px[start:start + chunk]
        rows = pixel[None, :, 0] - d[:, None, 1]
        cols = pixel[None, :, 1] + d[:, None, 0]
        dtm = map_coordinates(window, [rows.ravel(), cols.ravel()], order=1, mode="constant", cval=np.nan)
        r = weight * (heights - dtm.reshape(len(d), -1))
        r = np.nan_to_num(r, nan=10.0)
        r -= np.median(r, axis=1, keepdims=True)
        costs[start:start + chunk] = np.sum(np.minimum(r**2, 9.0), axis=1)
    best = int(np.argmin(costs))
    elsewhere = np.linalg.norm(grid - grid[best], axis=1) > _DISTINCT_M
    margin = float(costs[elsewhere].min() - costs[best]) if elsewhere.any() else np.inf
    return grid[best], margin


def _vertical(residuals, shift: np.ndarray) -> float:
    """The vertical offset at that shift: the median residual, in metres."""
    r0 = residuals(np.array([*shift, 0.0, 0.0]))
    r1 = residuals(np.array([*shift, 0.0, 1.0]))
    return float(-np.median(r0 / np.where(np.abs(r1 - r0) > 0, r1 - r0, 1.0)))
