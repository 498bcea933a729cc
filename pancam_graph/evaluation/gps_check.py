"""An estimate against GPS fixes: the antenna (the lever arm from the body) interpolated to each
fix's time, compared with the fixes in ENU (pyproj); whether the estimate's covariance holds
against them; and the score on fixes held out of the graph."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..records import GpsFix, Traverse
from .consistency import NeesAlongRun, nees
from .metrics import GPS_REFERENCE_STEP_M, TrajectoryMetrics, compare, decimated_length, fit_similarity_2d
from .timed import poses_at_times


@dataclass(frozen=True)
class HoldoutScore:
    """A configuration against GPS fixes kept out of every graph."""

    fixes: int
    rms_2d_m: float  # RMS horizontal distance of the estimate to the held-out fixes
    stated_drms_m: float  # the fixes' own stated 2-D RMS: what a perfect track would score
    # The 2-D similarity taking the estimate onto the fixes (Umeyama): how far the track is turned
    # (deg, anticlockwise) and scaled (%) against them, and what is left after it; None when degenerate.
    rotation_deg: float | None = None
    scale_pct: float | None = None
    rms_2d_after_similarity_m: float | None = None

    def as_dict(self) -> dict:
        return {"held_out_fixes": self.fixes, "rms_2d_m": self.rms_2d_m, "stated_drms_m": self.stated_drms_m,
                "drms_ratio": self.rms_2d_m / self.stated_drms_m, "rotation_deg": self.rotation_deg,
                "scale_pct": self.scale_pct, "rms_2d_after_similarity_m": self.rms_2d_after_similarity_m}


def gps_enu(traverse: Traverse, fixes: tuple[GpsFix, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fix times and the fixes converted to ENU (N, 3) with pyproj (default: the traverse's)."""
    fixes = traverse.gps_fixes if fixes is None else fixes
    if not fixes:
        return np.zeros(0), np.zeros((0, 3))
    enu = traverse.origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.h_m for f in fixes])
    return np.array([f.time_s for f in fixes]), enu


def antenna_positions(world_T_body: np.ndarray, lever_arm_m: np.ndarray) -> np.ndarray:
    """Where a point fixed in the body (the GPS antenna at its lever arm) is at each pose."""
    arm = np.asarray(lever_arm_m, dtype=float)
    return np.einsum("nij,j->ni", world_T_body[:, :3, :3], arm) + world_T_body[:, :3, 3]


def antenna_at_times(traverse: Traverse, world_T_body: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    stops = traverse.stops
    poses = poses_at_times(np.array([s.time_s for s in stops]), np.array([s.departure_s for s in stops]),
                           world_T_body, times_s)
    return antenna_positions(poses, traverse.gps_lever_arm_m)


def evaluate_against_gps(traverse: Traverse, world_T_body: np.ndarray,
                         fixes: tuple[GpsFix, ...] | None = None) -> TrajectoryMetrics | None:
    """The antenna, interpolated to each fix's time, against the fixes (unaligned)."""
    times, enu = gps_enu(traverse, fixes)
    if len(times) < 2:
        return None
    return compare(antenna_at_times(traverse, world_T_body, times), enu, "none",
                   reference_length_m=decimated_length(enu, GPS_REFERENCE_STEP_M))


def holdout_score(traverse: Traverse, world_T_body: np.ndarray, held_out: tuple[GpsFix, ...]) -> HoldoutScore | None:
    if not held_out:
        return None
    times, enu = gps_enu(traverse, held_out)
    antenna = antenna_at_times(traverse, world_T_body, times)
    rms = float(np.sqrt(np.mean(np.sum((antenna[:, :2] - enu[:, :2]) ** 2, axis=1))))
    drms = float(np.sqrt(np.mean([2.0 * f.sigma_horizontal_m**2 for f in held_out])))
    fit = fit_similarity_2d(antenna[:, :2], enu[:, :2])
    if fit is None:
        return HoldoutScore(len(held_out), rms, drms)
    rotation, scale, residuals = fit
    return HoldoutScore(len(held_out), rms, drms, float(np.degrees(rotation)), 100.0 * (scale - 1.0),
                        float(np.sqrt(np.mean(residuals**2))))


def nees_against_gps(traverse: Traverse, world_T_body: np.ndarray, covariances: np.ndarray,
                     vo_inliers: np.ndarray) -> NeesAlongRun | None:
    """Each fix's NEES against the antenna at its time, with the covariance of the stop nearest
    in time plus the fix's own (its stated sigmas): where there is no truth, whether the
    covariance holds against GPS. None without fixes in the stops' span."""
    times, enu = gps_enu(traverse)
    stop_times = np.array([s.time_s for s in traverse.stops])
    during = (times >= stop_times[0]) & (times <= stop_times[-1] + traverse.stops[-1].dwell_s)
    if not during.any():
        return None
    fixes = [f for f, inside in zip(traverse.gps_fixes, during, strict=True) if inside]
    times, enu = times[during], enu[during]
    after = np.minimum(np.searchsorted(stop_times, times), len(stop_times) - 1)  # stop times increase
    before = np.maximum(after - 1, 0)
    nearest = np.where(np.abs(times - stop_times[before]) <= np.abs(stop_times[after] - times), before, after)
    own = np.stack([np.diag([f.sigma_horizontal_m**2, f.sigma_horizontal_m**2, f.sigma_vertical_m**2])
                    for f in fixes])
    errors = antenna_at_times(traverse, world_T_body, times) - enu
    return NeesAlongRun(nees(errors, covariances[nearest] + own), vo_inliers[nearest], nearest, "gps")
