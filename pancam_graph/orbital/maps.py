"""Orbital maps on the local frame: where a map's posts are in local ENU, how far apart they are on
the ground, a map's georeference error (MapBias), and a map sampled from a height function (what
the simulation's orbiter sees).

A map's georeference error is a horizontal rigid motion of the whole map: a point at true ENU
w (east, north) appears in the map at R(rotation) w + (east, north), the rotation about the
local frame's origin (the traverse's start)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import GeodesyError
from ..geometry.geodesy import LocalFrame
from ..records import MapRaster

Height = Callable[[np.ndarray], np.ndarray]  # elevation (m, local up) at (N, 2) east-north points


@dataclass(frozen=True)
class MapBias:
    """A map's georeference error: map ENU = R(rotation_rad) x true ENU + (east_m, north_m)."""

    east_m: float = 0.0
    north_m: float = 0.0
    rotation_rad: float = 0.0

    def rotation(self) -> np.ndarray:
        c, s = np.cos(self.rotation_rad), np.sin(self.rotation_rad)
        return np.array([[c, -s], [s, c]])

    def to_map(self, xy: np.ndarray) -> np.ndarray:
        return np.atleast_2d(xy) @ self.rotation().T + [self.east_m, self.north_m]

    def from_map(self, xy: np.ndarray) -> np.ndarray:
        return (np.atleast_2d(xy) - [self.east_m, self.north_m]) @ self.rotation()


def ground_spacing(raster: MapRaster) -> tuple[float, float]:
    """(east-west, north-south) ground distance in metres between neighbouring posts at the
    raster's centre. A map's posts are square in map units, not always on the ground: an
    equidistant cylindrical CRS with its standard parallel at 0 (common for Mars DTMs) has posts
    cos(latitude) apart east-west (0.997 m for 1 m posts at Gale)."""
    rows, cols = raster.values.shape
    return _ground_spacing(raster.crs_wkt, raster.x0_m + cols * raster.post_m / 2,
                           raster.y0_m - rows * raster.post_m / 2, raster.post_m)


@lru_cache(maxsize=64)
def _ground_spacing(crs_wkt: str, x: float, y: float, post_m: float) -> tuple[float, float]:
    from pyproj import CRS, Proj, Transformer

    crs = CRS.from_wkt(crs_wkt)
    lon, lat = Transformer.from_crs(crs, crs.geodetic_crs, always_xy=True).transform(x, y)
    factors = Proj(crs).get_factors(lon, lat)  # map units per ground metre, along a parallel and a meridian
    return post_m / factors.parallel_scale, post_m / factors.meridional_scale


def ground_spacing_note(name: str, raster: MapRaster) -> str | None:
    """One line when the raster's posts are not square on the ground (by more than 0.01 %)."""
    east, north = ground_spacing(raster)
    if abs(east / north - 1.0) <= 1e-4:
        return None
    return (f"{name}: posts {raster.post_m:g} m apart in map units are {east:.4f} m apart east-west and "
            f"{north:.4f} m north-south on the ground (the map projection's scale differs between its axes there); "
            "registered on the ground's distances")


# A DTM whose height at the start is this far from the start's (and more than DATUM_SIGMAS times its
# stated vertical sigma) has heights in other units or on another datum than the traverse's
DATUM_MIN_M = 100.0
DATUM_SIGMAS = 20.0


def start_height_note(name: str, raster: MapRaster, frame: LocalFrame, start_enu: np.ndarray,
                      vertical_sigma_m: float) -> str | None:
    """One line when the DTM's height under the traverse's start is far from the start's own
    height above the body's surface: the map's bias absorbs a datum offset only within its
    stated vertical sigma, so registrations then fail as 'ambiguous' with no other hint."""
    from pyproj import CRS

    try:
        xy = frame.to_map(np.asarray(start_enu, dtype=float)[None, :], CRS.from_wkt(raster.crs_wkt))
    except GeodesyError:  # a CRS of another body: the orbital kind's check refuses the map, naming it
        return None
    dtm = float(raster.at(xy)[0])
    start_h = float(frame.to_geodetic(np.asarray(start_enu, dtype=float)[None, :])[0, 2])
    offset = dtm - start_h
    if not np.isfinite(dtm) or abs(offset) <= max(DATUM_MIN_M, DATUM_SIGMAS * vertical_sigma_m):
        return None
    return (f"{name}: its height under the start is {dtm:,.1f} m, the start's is {start_h:,.1f} m (both above "
            f"the body's surface): {offset:+,.0f} m apart, against a stated vertical sigma of {vertical_sigma_m:g} m "
            "(heights in other units, or on another datum?); its registrations will fail")


def post_enu(raster: MapRaster, frame: LocalFrame, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
    """(N, 3) local ENU of the raster's posts in the window rows x cols, row by row (the map
    taken at its word: its georeference as stated). Heights are the raster's values."""
    x, y = raster.centres()
    gx, gy = np.meshgrid(x[cols], y[rows])
    h = raster.values[rows, cols].astype(float).ravel()
    from pyproj import CRS

    return frame.from_map(np.column_stack([gx.ravel(), gy.ravel()]), h, CRS.from_wkt(raster.crs_wkt))


def sampled_raster(height: Height, frame: LocalFrame, lo_enu: np.ndarray, hi_enu: np.ndarray, post_m: float,
                   bias: MapBias = MapBias()) -> MapRaster:
    """A raster over the ENU box lo..hi (east, north) on the map projection's grid (LocalFrame.
    map_crs), one post every `post_m`, each post the true height at the ground point the map
    (with `bias`) puts there, as a height above the body's surface (the local frame is flat, the
    body is not: 15 cm apart at 1 km from the origin on Mars)."""
    crs = frame.map_crs()
    corners = frame.to_map(np.array([[lo_enu[0], hi_enu[1], 0.0], [hi_enu[0], lo_enu[1], 0.0]]), crs)
    x0, y0 = np.floor(corners[0, 0] / post_m) * post_m, np.ceil(corners[0, 1] / post_m) * post_m
    cols = int(np.ceil((corners[1, 0] - x0) / post_m))
    rows = int(np.ceil((y0 - corners[1, 1]) / post_m))
    raster = MapRaster(np.empty((rows, cols), np.float32), float(x0), float(y0), float(post_m), crs.to_wkt())
    gx, gy = np.meshgrid(*raster.centres())
    enu = frame.from_map(np.column_stack([gx.ravel(), gy.ravel()]), frame.h0_m, crs)
    enu[:, 2] = height(bias.from_map(enu[:, :2]))
    raster.values[:] = frame.to_geodetic(enu)[:, 2].reshape(rows, cols)
    return raster


def hillshade(dtm: np.ndarray, spacing_m: tuple[float, float], sun_azimuth_deg: float,
              sun_elevation_deg: float) -> np.ndarray:
    """Lambertian shading (0..1) of a height grid (rows north to south, posts `spacing_m` apart on
    the ground east-west and north-south) lit from the azimuth (clockwise from north) and
    elevation."""
    dz_dn, dz_de = np.gradient(dtm.astype(float), spacing_m[1], spacing_m[0])
    dz_dn = -dz_dn  # rows run south
    normal = np.stack([-dz_de, -dz_dn, np.ones_like(dz_de)])
    normal /= np.linalg.norm(normal, axis=0)
    az, el = np.deg2rad(sun_azimuth_deg), np.deg2rad(sun_elevation_deg)
    sun = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    return np.clip(np.tensordot(sun, normal, axes=1), 0.0, 1.0)
