"""Independent references for Mars geometry, sharing no code with the package under test.

- The sun's direction in Mars' body-fixed frame: astropy's built-in solar-system ephemeris
  (ERFA's, VSOP87-based) for the Sun and Mars, with light time and stellar aberration, turned
  into the body-fixed frame by the IAU WGCCRE 2015 rotation model of Mars (Archinal et al.
  2018, Celest. Mech. Dyn. Astr. 130:22, Table 2: pole right ascension and declination and
  prime meridian W with their periodic terms).
- The vertical: the normal of the IAU 2015 Mars ellipsoid (3,396.19 / 3,376.20 km) through a
  point, from its body-fixed position by Bowring's iteration; positions on the IAU 2015 sphere
  (R = 3,396.19 km, planetocentric latitude) in closed form.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

MARS_A_M, MARS_B_M = 3_396_190.0, 3_376_200.0  # IAU 2015 ellipsoid (Archinal et al. 2018, Table 5)
MARS_SPHERE_M = 3_396_190.0
C_KM_S = 299_792.458


def iau2015_mars_fixed_R_icrf(tdb_jd: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations from ICRF to Mars' body-fixed frame (IAU 2015 model)."""
    d = np.atleast_1d(tdb_jd) - 2451545.0
    t = d / 36525.0

    def s(a, b):
        return np.sin(np.deg2rad(a + b * t))

    def c(a, b):
        return np.cos(np.deg2rad(a + b * t))

    ra = (317.269202 - 0.10927547 * t + 0.000068 * s(198.991226, 19139.4819985)
          + 0.000238 * s(226.292679, 38280.8511281) + 0.000052 * s(249.663391, 57420.7251593)
          + 0.000009 * s(266.183510, 76560.6367950) + 0.419057 * s(79.398797, 0.5042615))
    dec = (54.432516 - 0.05827105 * t + 0.000051 * c(122.433576, 19139.9407476)
           + 0.000141 * c(43.058401, 38280.8753272) + 0.000031 * c(57.663379, 57420.7517205)
           + 0.000005 * c(79.476401, 76560.6495004) + 1.591274 * c(166.325722, 0.5042615))
    w = (176.049863 + 350.891982443297 * d + 0.000145 * s(129.071773, 19140.0328244)
         + 0.000157 * s(36.352167, 38281.0473591) + 0.000040 * s(56.668646, 57420.9295360)
         + 0.000001 * s(67.364003, 76560.2552215) + 0.000001 * s(104.792680, 95700.4387578)
         + 0.584542 * s(95.391654, 0.5042615))
    return np.einsum("nij,njk,nkl->nil", _rz(w), _rx(90.0 - dec), _rz(90.0 + ra))


def _rz(deg):
    a = np.deg2rad(deg)
    out = np.zeros((len(a), 3, 3))
    out[:, 0, 0] = out[:, 1, 1] = np.cos(a)
    out[:, 0, 1], out[:, 1, 0] = np.sin(a), -np.sin(a)
    out[:, 2, 2] = 1.0
    return out


def _rx(deg):
    a = np.deg2rad(deg)
    out = np.zeros((len(a), 3, 3))
    out[:, 1, 1] = out[:, 2, 2] = np.cos(a)
    out[:, 1, 2], out[:, 2, 1] = np.sin(a), -np.sin(a)
    out[:, 0, 0] = 1.0
    return out


def sun_mars_fixed(utc_s: np.ndarray) -> np.ndarray:
    """(N, 3) apparent unit vectors from Mars' centre to the Sun in Mars' body-fixed frame."""
    import astropy.units as u
    from astropy.coordinates import get_body_barycentric_posvel, solar_system_ephemeris
    from astropy.time import Time

    t = Time(np.atleast_1d(utc_s), format="unix", scale="utc")
    with solar_system_ephemeris.set("builtin"):
        mars, mars_v = get_body_barycentric_posvel("mars", t)
        light_s = np.zeros(len(t))
        for _ in range(3):  # the Sun where it was when the light left it
            sun, _ = get_body_barycentric_posvel("sun", t - light_s * u.s)
            r = (sun - mars).xyz.to_value(u.km).T
            light_s = np.linalg.norm(r, axis=1) / C_KM_S
    n = r / np.linalg.norm(r, axis=1)[:, None]
    beta = mars_v.xyz.to_value(u.km / u.s).T / C_KM_S  # stellar aberration, first order
    n = n + beta - np.sum(n * beta, axis=1)[:, None] * n
    n /= np.linalg.norm(n, axis=1)[:, None]
    return np.einsum("nij,nj->ni", iau2015_mars_fixed_R_icrf(t.tdb.jd), n)


def sphere_point(lat_deg, lon_deg, h_m) -> np.ndarray:
    """(N, 3) body-fixed position of planetocentric latitude, east longitude, height above the sphere."""
    lat, lon = np.deg2rad(np.atleast_1d(lat_deg)), np.deg2rad(np.atleast_1d(lon_deg))
    r = MARS_SPHERE_M + np.atleast_1d(h_m)
    return np.column_stack([r * np.cos(lat) * np.cos(lon), r * np.cos(lat) * np.sin(lon), r * np.sin(lat)])


def ellipsoid_normal(points: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of the IAU 2015 ellipsoid through body-fixed points (Bowring)."""
    x, y, z = np.atleast_2d(points).T
    p = np.hypot(x, y)
    e2 = 1.0 - (MARS_B_M / MARS_A_M) ** 2
    lat = np.arctan2(z, p * (1.0 - e2))
    for _ in range(10):
        n = MARS_A_M / np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - e2 * n / (n + h)))
    lon = np.arctan2(y, x)
    return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])


def enu_axes(point: np.ndarray) -> np.ndarray:
    """3x3 rows east, north, up (body-fixed) of the site at a body-fixed point, up the ellipsoid's normal."""
    up = ellipsoid_normal(point)[0]
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    return np.array([east, np.cross(up, east), up])


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between rows of two (N, 3) arrays of directions, in degrees."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    return np.rad2deg(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def mslice_locations(path: Path) -> dict[tuple[int, int], tuple[float, float]]:
    """MSLICE's ground-updated positions (the mission's science operations tool): (site, drive) ->
    planetocentric latitude, east longitude."""
    out = {}
    for location in ElementTree.parse(path).getroot():
        fields = {child.tag: child.text for child in location}
        out[(int(fields["site"]), int(fields["drive"]))] = (float(fields["lat"]), float(fields["lon"]))
    return out
