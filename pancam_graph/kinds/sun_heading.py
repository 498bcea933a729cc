"""Sun-sensor heading: at a site the rover images the sun with a WAC through its solar filter
and reads its accelerometers. The sun's direction measured in the body frame, against its
direction in the local ENU frame from an ephemeris, fixes the rover's attitude about every axis
but the sun line; gravity's direction fixes the tilt. Together they are the absolute attitude,
heading included: on Mars, where there is no GPS and no usable magnetic field, this is how a
rover finds its heading (MER's and Curiosity's sun finding). Without the tilt, the graph would
meet a sighting by tilting the rover as much as by turning it: dead reckoning's tilt is relative,
and its error grows along the traverse.

The factors are GTSAM's AttitudeFactorPose3 on the site's pose, one for the sun and one for
gravity: the measured body direction, rotated into the world, against the reference direction
(2 dof each, an angle per axis). The
ephemeris is pvlib's solar position (NREL's SPA) on Earth and marstime's Mars24 algorithm on
Mars. The sun is at infinity, so its direction in the local ENU frame (a Cartesian frame at the
origin) is the same wherever the rover is: it is computed at the origin. Gravity is not: the
vertical at the rover is the body ellipsoid's normal there (LocalFrame.up_at), which turns away
from the origin's by the distance over the body's radius (0.17 deg at 10 km on Mars).
"""

from __future__ import annotations

import datetime as dt
import warnings
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np
from pydantic import Field, model_validator

from ..errors import GeodesyError
from ..geometry.geodesy import LocalFrame
from ..graph import chi2
from ..graph.keys import X
from ..records import GroundTruth, Stop, Traverse
from .base import Kind, RowError, Section, StepCounts

Planet = Literal["earth", "mars"]
# Years the ephemerides are used in: ERFA's leap-second table starts in 1960 (UTC before it is
# not TT - 32.184 s - a whole number of seconds), pandas' timestamps (pvlib) end in 2262.
EPHEMERIS_YEARS = (1960, 2199)
_EPHEMERIS_UTC_S = (dt.datetime(EPHEMERIS_YEARS[0], 1, 1, tzinfo=dt.UTC).timestamp(),
                    dt.datetime(EPHEMERIS_YEARS[1] + 1, 1, 1, tzinfo=dt.UTC).timestamp())


class SunHeadingSettings(Section):
    """[estimator.sun_heading]: what the estimator assumes of the sun sightings."""

    planet: Planet | None = Field(None, description="whose ephemeris gives the sun's direction; default: the "
                                  "body of the traverse's origin")
    sigma_deg: float = Field(0.3, gt=0.0, le=30.0, description="1-sigma error of the measured sun direction, "
                             "per axis: the sun's centroid on the WAC (0.04 deg pixels) and, larger, the mast's "
                             "pan and tilt knowledge")
    tilt_sigma_deg: float = Field(0.1, gt=0.0, le=30.0, description="1-sigma error of the gravity direction "
                                  "from the accelerometers, per axis")
    gate_probability: float = Field(0.999, gt=0.5, lt=1.0, description="chi-square (2 dof) level above which "
                                    "a sighting is flagged after its update")


class SunSensor(Section):
    """A scenario's [sun_heading]: how the sun sightings are simulated."""

    enabled: bool = True
    planet: Planet | None = Field(None, description="default: the body of the scenario's origin")
    start_utc: dt.datetime | None = Field(None, description="the traverse's time 0; default (Earth): 09:00 local "
                                       "mean solar time at the origin on `date`")
    date: dt.date = dt.date(2026, 6, 21)
    sigma_deg: float = Field(0.3, ge=0.0, le=30.0, description="1-sigma error of a sighting, per axis")
    tilt_sigma_deg: float = Field(0.1, ge=0.0, le=30.0, description="1-sigma error of the accelerometers' "
                                  "gravity direction, per axis")
    min_elevation_deg: float = Field(10.0, ge=-5.0, le=89.0, description="no sighting with the sun lower "
                                     "(horizon, mast and refraction)")

    @model_validator(mode="after")
    def _check(self) -> SunSensor:
        if self.planet == "mars" and self.start_utc is None:
            raise ValueError("planet 'mars' needs start_utc (local solar time on Mars is not derived here)")
        year = self.date.year if self.start_utc is None else self.start_utc.year
        if not EPHEMERIS_YEARS[0] <= year <= EPHEMERIS_YEARS[1]:
            what = f"date {self.date}" if self.start_utc is None else f"start_utc {self.start_utc}"
            raise ValueError(f"{what}: the sun's ephemerides are used for years {EPHEMERIS_YEARS[0]}-"
                             f"{EPHEMERIS_YEARS[1]}")
        return self

@dataclass(frozen=True)
class SunSighting:
    """The sun's direction and the up direction (against gravity) in the body frame, measured at a
    stop at a UTC time (seconds since 1970)."""

    stop: int
    utc_s: float
    sun_body: np.ndarray  # (3,) unit vector
    up_body: np.ndarray  # (3,) unit vector


def sun_directions_enu(planet: Planet, frame: LocalFrame, utc_s: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors towards the sun in the local ENU frame at `frame`'s origin, as a sun
    sensor sees it (apparent: light time and aberration, and on Earth refraction, included)."""
    utc_s = np.atleast_1d(np.asarray(utc_s, dtype=float))
    outside = ~((utc_s >= _EPHEMERIS_UTC_S[0]) & (utc_s < _EPHEMERIS_UTC_S[1]))
    if outside.any():
        raise GeodesyError(f"UTC {utc_s[outside][0]:g} s since 1970: the sun's ephemerides are used for years "
                           f"{EPHEMERIS_YEARS[0]}-{EPHEMERIS_YEARS[1]}")
    if planet == "earth":
        # pvlib (and pandas under it) only when a traverse has sightings: every process imports kinds
        import pandas as pd
        from pvlib.solarposition import get_solarposition

        times = pd.to_datetime(utc_s, unit="s", utc=True)
        sun = get_solarposition(times, frame.lat0_deg, frame.lon0_deg, altitude=frame.h0_m)
        elevation = np.deg2rad(sun["apparent_elevation"].to_numpy())
        azimuth = np.deg2rad(sun["azimuth"].to_numpy())  # clockwise from north
        return np.column_stack([np.cos(elevation) * np.sin(azimuth), np.cos(elevation) * np.cos(azimuth),
                                np.sin(elevation)])
    import marstime

    j2000 = _tt_days_since_j2000(utc_s)
    ls = np.deg2rad(marstime.Mars_Ls(j2000))
    # A direction in the body-fixed Cartesian frame needs the planetocentric declination; Mars24's
    # solar_declination is the planetographic one, 0.25 deg sin Ls larger (Allison & McEwen 2000)
    declination = np.arcsin(0.42565 * np.sin(ls))
    subsolar_east = -np.deg2rad(marstime.subsolar_longitude(j2000))  # Mars24 gives it west-positive
    sun_fixed = np.column_stack([np.cos(declination) * np.cos(subsolar_east),
                                 np.cos(declination) * np.sin(subsolar_east), np.sin(declination)])
    return sun_fixed @ frame.enu_R_fixed().T


def _tt_days_since_j2000(utc_s: np.ndarray) -> np.ndarray:
    """Terrestrial Time in days since J2000 of UTC seconds since 1970, with ERFA's leap seconds
    (marstime's own table stops in 2012: 2 s, 0.008 deg of Mars' rotation, short since 2017)."""
    import erfa

    days, seconds = np.divmod(np.asarray(utc_s, dtype=float), 86400.0)
    with warnings.catch_warnings():
        # past the table's last entry, its last TAI - UTC holds (no leap second is announced)
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        tai = erfa.utctai(2440587.5 + days, seconds / 86400.0)
        tt = erfa.taitt(*tai)
    return (tt[0] - 2451545.0) + tt[1]


def start_utc_s(sensor: SunSensor, frame: LocalFrame) -> float:
    """The traverse's time 0 as UTC seconds since 1970."""
    if sensor.start_utc is not None:
        start = sensor.start_utc if sensor.start_utc.tzinfo else sensor.start_utc.replace(tzinfo=dt.UTC)
    else:  # 09:00 local mean solar time: UTC + longitude / 15 h
        start = (dt.datetime(sensor.date.year, sensor.date.month, sensor.date.day, 9, tzinfo=dt.UTC)
                 - dt.timedelta(hours=frame.lon0_deg / 15.0))
    return start.timestamp()


def _perturbed(direction: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """A unit vector off `direction` by sigma_rad (1 sigma) along each of two perpendicular axes."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(direction[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(direction, helper)
    a /= np.linalg.norm(a)
    b = np.cross(direction, a)
    out = direction + sigma_rad * (rng.normal() * a + rng.normal() * b)
    return out / np.linalg.norm(out)


def _unit(line: int, name: str, xyz) -> np.ndarray:
    """A direction as written (Unit3 normalizes it; renormalizing here would change the last bits)."""
    with np.errstate(over="ignore"):  # a norm of 1e308s is inf, and refused below
        norm = float(np.linalg.norm(xyz))
    if not 0.99 < norm < 1.01:
        raise RowError(line, f"{name}_x, {name}_y, {name}_z must be a unit vector, got length {norm:.3g}")
    return np.asarray(xyz, dtype=float)


class SunHeading(Kind):
    name = "sun_heading"
    order = 7
    Settings = SunHeadingSettings
    Sensor = SunSensor
    columns = ("stop", "utc_s", "sun_x", "sun_y", "sun_z", "up_x", "up_y", "up_z")
    step_counters = {"sun_sightings": 0, "sun_flagged": 0}

    records = "sun sightings"

    @classmethod
    def check_scenario(cls, scenario) -> None:
        body = scenario.origin.body
        sun = getattr(scenario, cls.name, None)
        if sun is not None and sun.enabled:
            if sun.planet not in (None, body):
                raise ValueError(f"[sun_heading] planet = {sun.planet!r} but the origin is on {body}")
            if body == "mars" and sun.start_utc is None:
                raise ValueError("[sun_heading] on mars needs start_utc (local solar time on Mars is not derived here)")
        estimated = getattr(scenario.estimator, cls.name, None)
        if estimated is not None and estimated.planet not in (None, body):
            raise ValueError(f"[estimator.sun_heading] planet = {estimated.planet!r} but the origin is on {body}")

    # -- records -------------------------------------------------------------------------------

    @classmethod
    def simulate(cls, sensor: SunSensor, traverse: Traverse, truth: GroundTruth,
                 rng: np.random.Generator) -> tuple[SunSighting, ...]:
        """A sighting at every site with the sun high enough, from the true attitude."""
        sites = [s for s in traverse.stops if s.is_site]
        if not sites:
            return ()
        utc = start_utc_s(sensor, traverse.origin) + np.array([s.time_s for s in sites])
        directions = sun_directions_enu(sensor.planet or traverse.origin.body, traverse.origin, utc)
        verticals = traverse.origin.up_at(np.array([truth.world_T_body[s.index][:3, 3] for s in sites]))
        low = np.sin(np.deg2rad(sensor.min_elevation_deg))
        out = []
        for stop, t, n, up_world in zip(sites, utc, directions, verticals, strict=True):
            if n[2] < low:  # the sun's elevation, near enough: the vertical turns 0.17 deg in 10 km
                continue
            body_R_world = truth.world_T_body[stop.index][:3, :3].T
            sun = _perturbed(body_R_world @ n, np.deg2rad(sensor.sigma_deg), rng)
            up = _perturbed(body_R_world @ up_world, np.deg2rad(sensor.tilt_sigma_deg), rng)
            out.append(SunSighting(stop.index, float(t), sun, up))
        return tuple(out)

    @classmethod
    def to_rows(cls, records: tuple[SunSighting, ...]) -> list[tuple[float, ...]]:
        return [(s.stop, s.utc_s, *s.sun_body, *s.up_body) for s in records]

    @classmethod
    def from_rows(cls, rows, traverse: Traverse) -> tuple[SunSighting, ...]:
        out, seen = [], {}
        for line, (stop, utc_s, *numbers) in rows:
            if stop != int(stop) or not 0 <= stop < len(traverse.stops):
                raise RowError(line, f"stop {stop:g} is not one of the traverse's stops 0..{len(traverse.stops) - 1}")
            if int(stop) in seen:
                raise RowError(line, f"stop {int(stop)} has a sighting already (line {seen[int(stop)]}): one a stop")
            seen[int(stop)] = line
            if not _EPHEMERIS_UTC_S[0] <= utc_s < _EPHEMERIS_UTC_S[1]:
                raise RowError(line, f"utc_s {utc_s:g} is outside the years {EPHEMERIS_YEARS[0]}-"
                                     f"{EPHEMERIS_YEARS[1]} the sun's ephemerides are used for")
            sun, up = _unit(line, "sun", numbers[:3]), _unit(line, "up", numbers[3:])
            out.append(SunSighting(int(stop), utc_s, sun, up))
        return tuple(out)

    # -- the step ------------------------------------------------------------------------------

    def __init__(self, localizer):
        super().__init__(localizer)
        settings: SunHeadingSettings = localizer.estimator.sun_heading
        sightings = localizer.traverse.measurements.get(self.name, ())
        origin = localizer.traverse.origin
        references = sun_directions_enu(settings.planet or origin.body, origin, [s.utc_s for s in sightings])
        self._at_stop = {s.stop: (s, n) for s, n in zip(sightings, references, strict=True)}
        self.sigma_rad = np.deg2rad(settings.sigma_deg)
        self.gate = chi2.quantile(settings.gate_probability, 2)
        self._sun_model = gtsam.noiseModel.Isotropic.Sigma(2, self.sigma_rad)
        self._tilt_model = gtsam.noiseModel.Isotropic.Sigma(2, np.deg2rad(settings.tilt_sigma_deg))
        self.used = 0
        self.flagged: list[int] = []
        self.largest_mahalanobis2 = 0.0

    def add(self, stop: Stop, counts: StepCounts) -> None:
        if stop.index in self._at_stop:
            sighting, reference = self._at_stop[stop.index]
            key = X(stop.index)
            # the vertical where the rover is predicted to be: 1 km off turns it by 0.017 deg on Mars
            up = self.loc.traverse.origin.up_at(self.loc.smoother.pose(key).translation()[None, :])[0]
            self.loc.smoother.add(gtsam.AttitudeFactorPose3(key, gtsam.Unit3(reference), self._sun_model,
                                                            gtsam.Unit3(sighting.sun_body)))
            self.loc.smoother.add(gtsam.AttitudeFactorPose3(key, gtsam.Unit3(up), self._tilt_model,
                                                            gtsam.Unit3(sighting.up_body)))
            self.used += 1
            counts.add("sun_sightings")

    def after_update(self, stop: Stop, counts: StepCounts) -> None:
        if stop.index not in self._at_stop:
            return
        sighting, reference = self._at_stop[stop.index]
        seen = self.loc.smoother.pose(X(stop.index)).rotation().matrix() @ sighting.sun_body
        angle = np.arctan2(np.linalg.norm(np.cross(seen, reference)), seen @ reference)
        d2 = float((angle / self.sigma_rad) ** 2)
        self.largest_mahalanobis2 = max(self.largest_mahalanobis2, d2)
        if d2 > self.gate:
            self.flagged.append(stop.index)
            counts.add("sun_flagged")

    def counters(self) -> dict:
        return {"sun_sightings_used": self.used, "sun_sightings_flagged": len(self.flagged),
                "sun_largest_mahalanobis2": self.largest_mahalanobis2}
