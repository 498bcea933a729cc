"""Design trades of Chapter 3: mapping error, two-stop VO and its growth, the HRC's gain, and
the two-site bundle adjustment (optimal field of view, longest site spacing for 1 %).

Every function takes an `AnalysisRig` (any rig: baseline, focal length, FOV, optional HRC)
and an `Assumptions` (pixel noise, layouts), so every figure can say what it assumed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from ..geometry.rig import Rig, rig_preset
from .stereo import hrc_point_covariance, point_covariance, rotate_covariance
from .transform import TransformModel, position_covariance, propagate, transform_covariance


@dataclass(frozen=True)
class AnalysisRig:
    """What the error model needs of a stereo rig (and of an HRC paired with its left camera)."""

    name: str
    baseline_m: float
    focal_px: float
    fov_deg: float  # horizontal
    hrc_baseline_m: float | None = None  # HRC to the left camera
    hrc_focal_px: float | None = None
    hrc_fov_deg: float | None = None

    @property
    def has_hrc(self) -> bool:
        return self.hrc_focal_px is not None

    @classmethod
    def from_rig(cls, rig: Rig, name: str | None = None) -> AnalysisRig:
        fov = lambda camera: float(np.rad2deg(2 * np.arctan(camera.width / 2 / camera.fx)))  # noqa: E731
        if rig.hrc is None:
            return cls(name or rig.name, rig.baseline_m, rig.wac.fx, fov(rig.wac))
        return cls(name or rig.name, rig.baseline_m, rig.wac.fx, fov(rig.wac), rig.hrc_offset_m, rig.hrc.fx,
                   fov(rig.hrc))

    @classmethod
    def preset(cls, name: str) -> AnalysisRig:
        return cls.from_rig(rig_preset(name))


@dataclass(frozen=True)
class Assumptions:
    """One set of assumptions for every rig; written next to every result."""

    sigma_px: float = 0.5  # matching error of x_l, x_r: "up to half of the pixel size" (the dissertation, 3.2.1)
    relative_error_target: float = 0.01  # 1 % of the site spacing
    relative_error: str = "DRMS: sqrt(trace of the 2x2 covariance of site 2's position) / spacing"
    ba_model: TransformModel = "similarity"  # the dissertation's 4-parameter (a, b, c, d) transform
    ba_rays: int = 3  # tie points: rays evenly spaced across the FOV from site 1, FOV edges included,
    ba_ranges: int = 3  # ... times ranges D j / (ranges + 1), j = 1..ranges, along each ray
    ba_fov_reference_spacing_m: float = 20.0  # the optimal FOV is found at this site spacing (the dissertation's)
    pointing: str = "each tie point is imaged with the pair's centre line on it (mast pointed); the HRC too"
    vo_step_m: float = 2.0  # two-stop VO: the rover moves this far along the range direction
    vo_max_range_m: float = 20.0  # features up to this range (the dissertation: error > 0.5 m beyond ~20 m)
    vo_min_range_m: float = 2.0
    vo_feature_spacing_m: float = 1.0  # features on a square grid with this spacing inside the FOV wedge
    elevation: str = "Y held constant (the dissertation's planar model): only (X, Z) errors are propagated"

    @property
    def tie_points(self) -> int:
        return self.ba_rays * self.ba_ranges

    def as_dict(self) -> dict:
        return asdict(self) | {"tie_points": self.tie_points}


# -- mapping -------------------------------------------------------------------------------

def fov_grid(fov_deg: float, max_range_m: float, spacing_m: float, min_range_m: float = 0.0) -> np.ndarray:
    """Points (N, 2) on a square grid inside the camera's FOV wedge, min_range <= r <= max_range."""
    half = np.deg2rad(fov_deg) / 2
    xs = np.arange(-max_range_m, max_range_m + 1e-9, spacing_m)
    zs = np.arange(spacing_m, max_range_m + 1e-9, spacing_m)
    x, z = (a.ravel() for a in np.meshgrid(xs, zs))
    r = np.hypot(x, z)
    keep = (np.abs(np.arctan2(x, z)) <= half + 1e-12) & (r <= max_range_m + 1e-9) & (r >= min_range_m)
    return np.column_stack([x[keep], z[keep]])


def mapping_covariances(rig: AnalysisRig, points: np.ndarray, sigma_px: float, hrc: bool = False) -> np.ndarray:
    """Eq. (3.3) (or (3.11) with `hrc`) at each point of the left camera frame, (N, 2, 2)."""
    if hrc:
        return np.stack([hrc_point_covariance(x, z, rig.hrc_baseline_m, rig.hrc_focal_px, rig.focal_px, sigma_px)
                         for x, z in points])
    return np.stack([point_covariance(x, z, rig.baseline_m, rig.focal_px, sigma_px) for x, z in points])


def in_hrc_fov(rig: AnalysisRig, points: np.ndarray, hrc_fov_deg: float) -> np.ndarray:
    """Points inside the HRC's FOV when it looks along the WACs' axis from its place on the bar."""
    return np.abs(np.arctan2(points[:, 0] - rig.hrc_baseline_m, points[:, 1])) <= np.deg2rad(hrc_fov_deg) / 2


# -- two-stop VO and its growth -------------------------------------------------------------

@dataclass(frozen=True)
class TwoStopVO:
    features: int
    step_m: float
    parameter_cov: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    position_cov: np.ndarray  # (2, 2) of stop 2 in stop 1's frame

    @property
    def sigma_m(self) -> float:
        return float(np.sqrt(np.trace(self.position_cov)))


def two_stop_vo(rig: AnalysisRig, a: Assumptions, step_m: float | None = None, max_range_m: float | None = None,
                hrc_fov_deg: float | None = None, model: TransformModel = "similarity") -> TwoStopVO:
    """Eqs. (3.4)-(3.10): the rover moves `step_m` straight along Z; the features seen from both
    stops (inside both FOV wedges and ranges) give the transform and stop 2's covariance.
    With `hrc_fov_deg`, features inside the HRC's FOV take the HRC + left-WAC covariance (3.11)."""
    step = a.vo_step_m if step_m is None else step_m
    max_range = a.vo_max_range_m if max_range_m is None else max_range_m
    first = fov_grid(rig.fov_deg, max_range, a.vo_feature_spacing_m, a.vo_min_range_m)
    second = first - np.array([0.0, step])
    half = np.deg2rad(rig.fov_deg) / 2
    r2 = np.hypot(*second.T)
    both = (second[:, 1] > 0) & (np.abs(np.arctan2(second[:, 0], second[:, 1])) <= half) & (r2 >= a.vo_min_range_m)
    first, second = first[both], second[both]
    cov_first = mapping_covariances(rig, first, a.sigma_px)
    cov_second = mapping_covariances(rig, second, a.sigma_px)
    if hrc_fov_deg is not None:
        for points, covs in ((first, cov_first), (second, cov_second)):
            seen = in_hrc_fov(rig, points, hrc_fov_deg)
            if seen.any():
                covs[seen] = mapping_covariances(rig, points[seen], a.sigma_px, hrc=True)
    # source: stop 2's observations; target: stop 1's; stop 2 is the source frame's origin
    parameter_cov, rotation, translation = transform_covariance(second, cov_second, first, cov_first, model)
    return TwoStopVO(len(first), step, parameter_cov, rotation, translation,
                     position_covariance(parameter_cov, rotation, np.zeros(2), model))


def vo_growth(rig: AnalysisRig, a: Assumptions, stops: int, model: TransformModel = "similarity") -> np.ndarray:
    """1-sigma (DRMS) position error at stops 1..n of straight VO with equal steps, (3.12)-(3.13)."""
    step = two_stop_vo(rig, a, model=model)
    covs = propagate([(step.parameter_cov, step.rotation, step.translation)] * stops, model)
    return np.array([np.sqrt(np.trace(c)) for c in covs])


# -- two-site bundle adjustment ---------------------------------------------------------------

def tie_point_layout(spacing_m: float, fov_deg: float, rays: int, ranges: int) -> np.ndarray:
    """Tie points in site 1's frame (site 2 at (0, spacing) facing back): `rays` rays evenly
    spread over the FOV (edges included), `ranges` points along each between the sites."""
    bearings = np.linspace(-np.deg2rad(fov_deg) / 2, np.deg2rad(fov_deg) / 2, rays) if rays > 1 else np.zeros(1)
    distances = spacing_m * np.arange(1, ranges + 1) / (ranges + 1)
    return np.array([(r * np.sin(b), r * np.cos(b)) for b in bearings for r in distances])


def _pointed_covariance(rig: AnalysisRig, point: np.ndarray, sigma_px: float, hrc: bool) -> np.ndarray:
    """A tie point's (X, Z) covariance in the site frame, imaged with the pair pointed at it."""
    r, bearing = float(np.hypot(*point)), float(np.arctan2(point[0], point[1]))
    if hrc:
        cov = hrc_point_covariance(rig.hrc_baseline_m / 2, r, rig.hrc_baseline_m, rig.hrc_focal_px, rig.focal_px,
                                   sigma_px)
    else:
        cov = point_covariance(rig.baseline_m / 2, r, rig.baseline_m, rig.focal_px, sigma_px)
    return rotate_covariance(cov, bearing)


@dataclass(frozen=True)
class TwoSiteBA:
    spacing_m: float
    fov_deg: float
    tie_points: np.ndarray  # (N, 2) in site 1's frame
    position_cov: np.ndarray  # (2, 2) of site 2 in site 1's frame

    @property
    def relative_error(self) -> float:
        return float(np.sqrt(np.trace(self.position_cov)) / self.spacing_m)


def two_site_ba(rig: AnalysisRig, a: Assumptions, spacing_m: float, fov_deg: float, hrc: bool = False,
                model: TransformModel | None = None) -> TwoSiteBA:
    """Site 2's covariance from tie points seen forward from site 1 and backward from site 2
    (Fig. 3.12), through the same adjustment as VO. With `hrc` every tie point is also imaged
    by the HRC (the mast points it) and takes the HRC + left-WAC covariance (3.11)."""
    points = tie_point_layout(spacing_m, fov_deg, a.ba_rays, a.ba_ranges)
    at_site2 = np.column_stack([-points[:, 0], spacing_m - points[:, 1]])  # turned round, facing site 1
    cov1 = np.stack([_pointed_covariance(rig, p, a.sigma_px, hrc) for p in points])
    cov2 = np.stack([_pointed_covariance(rig, p, a.sigma_px, hrc) for p in at_site2])
    model = model or a.ba_model
    parameter_cov, rotation, _ = transform_covariance(at_site2, cov2, points, cov1, model)
    return TwoSiteBA(spacing_m, fov_deg, points, position_covariance(parameter_cov, rotation, np.zeros(2), model))


def optimal_fov(rig: AnalysisRig, a: Assumptions, hrc: bool = False) -> float:
    """The FOV (deg) minimising the relative error at the reference spacing: a 1-degree scan
    over 10-175 deg, refined around its best point."""
    spacing = a.ba_fov_reference_spacing_m
    error = lambda fov: two_site_ba(rig, a, spacing, fov, hrc).relative_error  # noqa: E731
    scan = np.arange(10.0, 175.5, 1.0)
    best = float(scan[int(np.argmin([error(f) for f in scan]))])
    refined = minimize_scalar(error, bounds=(max(best - 1, 10.0), min(best + 1, 175.0)), method="bounded")
    return float(refined.x)


def max_site_spacing(rig: AnalysisRig, a: Assumptions, fov_deg: float, hrc: bool = False,
                     model: TransformModel | None = None) -> float:
    """The longest spacing (m) whose relative error stays at the target (1 %)."""
    excess = lambda d: two_site_ba(rig, a, d, fov_deg, hrc, model).relative_error - a.relative_error_target  # noqa: E731
    lo, hi = 0.5, 5000.0
    if excess(lo) > 0:
        return 0.0
    if excess(hi) < 0:
        return hi
    return float(brentq(excess, lo, hi, xtol=1e-4))
