"""GPS fixes, each at its own time: a fix taken while the rover stands at a stop constrains that
stop's pose; a fix taken while driving constrains a pose inserted at the fix time, the motion
between the two stops being split there by time (see `Localizer.step`). ENU from pyproj, the
antenna lever arm, a robust kernel, and a chi-square test at the updated estimate."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..graph import chi2, factors, noise
from ..graph.keys import X
from ..records import GpsFix, Stop, Traverse
from .base import Kind, RowError, Section

TIME_TOLERANCE_S = 1e-3  # a fix this close to a stop's time is taken at the stop
_REASONS_KEPT = 20
MAX_FIX_DISTANCE_M = 100e3  # beyond this, a fix is of another place (and the tangent plane bends away by 800 m)
MAX_HEIGHT_M = 100e3  # a receiver's height beyond this is no height on or over the ground


class GpsSettings(Section):
    """[estimator.gps]"""

    kernel: Literal["huber", "cauchy", "none"] = "huber"
    outlier_probability: float = Field(0.99, gt=0.5, lt=1.0, description="chi-square (3 dof) level above which a "
                                       "fix is flagged as an outlier after its update")
    time_association: Literal["interpolate", "nearest_stop"] = Field(
        "interpolate", description="interpolate: a fix between stops constrains a pose inserted at its time; "
        "nearest_stop: it is attached to the stop nearest in time (the old behaviour, for comparison)")
    max_gap_s: float = Field(600.0, gt=0.0, description="a fix inside a drive longer than this between two motion "
                             "estimates is refused")


class Gps(Kind):
    name = "gps"
    order = 5
    absolute = True

    @classmethod
    def scenario_unavailable(cls, scenario) -> str | None:
        return None if scenario.gps.enabled else "the scenario simulates no GPS fixes (its [gps] is not enabled)"

    @classmethod
    def check_scenario(cls, scenario) -> None:
        if scenario.origin.body == "mars" and scenario.gps.enabled:
            raise ValueError("origin on mars: there is no GPS on Mars; set [gps] enabled = false")
    # fixes used in a stop's update (at the stop or on the drive to it), those failing the
    # chi-square test at the updated estimate, and the largest squared Mahalanobis distance
    step_counters = {"gps_fixes": 0, "gps_outliers": 0, "gps_mahalanobis2": None}
    counter_defaults = {"gps_fixes_used": 0, "gps_outliers": 0}
    Settings = GpsSettings

    records = "GPS fixes"
    # its observation-folder table, gps.csv (h ellipsoidal; a `stop` column of older folders is
    # ignored: each fix is used at its own time)
    columns = ("time_s", "lat_deg", "lon_deg", "h_m", "sigma_h_m", "sigma_v_m")

    @classmethod
    def to_rows(cls, records: tuple[GpsFix, ...]) -> list[tuple[float, ...]]:
        return [(f.time_s, f.lat_deg, f.lon_deg, f.h_m, f.sigma_horizontal_m, f.sigma_vertical_m) for f in records]

    @classmethod
    def from_rows(cls, rows, traverse: Traverse) -> tuple[GpsFix, ...]:
        """Fixes in time order: times must increase."""
        fixes: list[GpsFix] = []
        for line, (t, lat, lon, h, sigma_h, sigma_v) in rows:
            if not -90 <= lat <= 90:
                raise RowError(line, f"lat_deg {lat:g}: expected -90..90 degrees")
            if not -180 <= lon <= 360:
                raise RowError(line, f"lon_deg {lon:g}: expected -180..360 degrees")
            if not -MAX_HEIGHT_M <= h <= MAX_HEIGHT_M:
                raise RowError(line, f"h_m {h:g}: expected within {MAX_HEIGHT_M / 1000:.0f} km of the ellipsoid")
            if not (sigma_h > 0 and sigma_v > 0):
                raise RowError(line, f"sigma_h_m {sigma_h:g}, sigma_v_m {sigma_v:g}: expected positive metres")
            if fixes and t <= fixes[-1].time_s:
                raise RowError(line, f"time_s {t:g} does not increase (previous fix {fixes[-1].time_s:g})")
            if lat == 0 and lon == 0:
                raise RowError(line, "lat_deg = lon_deg = 0: a receiver's no-fix marker, not a position (leave the "
                               "row out)")
            fixes.append(GpsFix(t, lat, lon, h, sigma_h, sigma_v))
        if fixes:
            enu = traverse.origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes],
                                         [f.h_m for f in fixes])
            far = np.flatnonzero(np.linalg.norm(enu, axis=1) > MAX_FIX_DISTANCE_M)
            if far.size:
                (line, _), distance = rows[far[0]], np.linalg.norm(enu[far[0]])
                raise RowError(line, f"the fix lies {distance / 1000:.0f} km from the traverse's origin (at most "
                               f"{MAX_FIX_DISTANCE_M / 1000:.0f} km): not a fix of this traverse")
        return tuple(fixes)

    def __init__(self, localizer):
        super().__init__(localizer)
        est, settings = localizer.estimator, localizer.estimator.gps
        self.gate = chi2.quantile(settings.outlier_probability, 3)
        self.interpolate = settings.time_association == "interpolate"
        self.max_gap_s = settings.max_gap_s
        self.refused: list[str] = []
        self.used = self.outliers = 0
        self.refused_count = 0
        self._pending: list[tuple[int, GpsFix, np.ndarray]] = []  # this stop's (key, fix, ENU)
        fixes = localizer.traverse.gps_fixes
        self._times_s = np.array([f.time_s for f in fixes])
        enu = localizer.traverse.origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes],
                                               [f.h_m for f in fixes])
        self._enu = dict(zip((f.time_s for f in fixes), enu, strict=True))  # converted once, by time
        self._kernel = settings.kernel, est.kernel_k(settings.kernel)
        first = localizer.traverse.stops[0].time_s
        for fix in fixes:
            if fix.time_s < first - TIME_TOLERANCE_S:
                self._refuse(fix, f"before the first stop (t = {first:.3f} s): no motion estimate reaches it")

    def _refuse(self, fix: GpsFix, reason: str) -> None:
        self.refused_count += 1
        if len(self.refused) < _REASONS_KEPT:
            self.refused.append(f"fix at t = {fix.time_s:.3f} s: {reason}")

    def _window(self, prev: Stop | None, stop: Stop) -> list[GpsFix]:
        after = stop.time_s - TIME_TOLERANCE_S if prev is None else prev.departure_s
        lo, hi = np.searchsorted(self._times_s, [after, stop.departure_s], side="right")
        return list(self.loc.traverse.gps_fixes[lo:hi])  # after < time_s <= departure

    def _drive_too_long(self, prev: Stop, stop: Stop) -> bool:
        return stop.time_s - prev.departure_s > self.max_gap_s

    def pose_times(self, prev: Stop, stop: Stop) -> list[float]:
        if not self.interpolate or self._drive_too_long(prev, stop):
            return []
        return [f.time_s for f in self._window(prev, stop)
                if prev.departure_s + TIME_TOLERANCE_S < f.time_s < stop.time_s - TIME_TOLERANCE_S]

    def _key(self, prev: Stop | None, stop: Stop, fix: GpsFix) -> int | None:
        """The pose the fix constrains, or None (refused)."""
        t = fix.time_s
        if prev is None or t >= stop.time_s - TIME_TOLERANCE_S:
            return X(stop.index)  # at the stop, or while standing there
        if t <= prev.departure_s + TIME_TOLERANCE_S:
            return X(prev.index)
        if not self.interpolate:  # nearest stop in time
            return X(prev.index) if t - prev.departure_s < stop.time_s - t else X(stop.index)
        if self._drive_too_long(prev, stop):
            self._refuse(fix, f"inside a {stop.time_s - prev.departure_s:.0f} s drive between stops {prev.index} "
                              f"and {stop.index}, longer than [estimator.gps] max_gap_s = {self.max_gap_s:g} s")
            return None
        return self.loc.pose_key_at(t)

    def add(self, stop: Stop, counts) -> None:
        prev = self.loc.previous_stop
        lever = self.loc.traverse.gps_lever_arm_m
        for fix in self._window(prev, stop):
            key = self._key(prev, stop, fix)
            if key is None:
                continue
            enu = self._enu[fix.time_s]
            model = noise.robust(self._kernel[0], noise.gps_position(fix.sigma_horizontal_m, fix.sigma_vertical_m),
                                 self._kernel[1])
            self.loc.smoother.add(factors.gps_at(key, enu, lever, model))
            self._pending.append((key, fix, enu))

    def after_update(self, stop: Stop, counts) -> None:
        lever = self.loc.traverse.gps_lever_arm_m
        for key, fix, enu in self._pending:
            antenna = self.loc.smoother.pose(key).transformFrom(lever)
            sigmas = np.array([fix.sigma_horizontal_m, fix.sigma_horizontal_m, fix.sigma_vertical_m])
            d2 = float(np.sum(((antenna - enu) / sigmas) ** 2))
            counts.add("gps_fixes")
            counts.add("gps_outliers", int(d2 > self.gate))
            counts["gps_mahalanobis2"] = max(d2, counts.get("gps_mahalanobis2") or 0.0)
            self.used += 1
            self.outliers += int(d2 > self.gate)
        self._pending.clear()

    def finish(self) -> None:
        last = self.loc.traverse.stops[-1]
        for fix in self.loc.traverse.gps_fixes:
            if fix.time_s > last.departure_s:
                self._refuse(fix, f"after the last stop's departure (t = {last.departure_s:.3f} s)")

    def counters(self) -> dict:
        return {"gps_fixes_used": self.used, "gps_outliers": self.outliers, "gps_fixes_refused": self.refused_count,
                "gps_refusals": self.refused}
