"""The localization product: a trajectory as planetary GIS tools take it. Per stop: the rover
motion counter (site, drive), the position in the local frame, map easting and northing, the
planetocentric and planetodetic latitude, east longitude and height, roll, pitch and yaw, and the
1-sigma horizontal ellipse. Written as CSV (column names after MSL's published localization table,
`localized_interp.csv`, where it has them), as a GeoPackage in the body's own geographic CRS
(IAU 2015 on Mars: QGIS), and as GeoJSON longitude/latitude (MMGIS)."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import WriteFailed
from ..geometry.geodesy import LocalFrame
from .pds import BODY_R_ROVER, ENU_R_SITE
from .tables import write_csv

# the world's east-north-up and the body's forward-left-up -> the missions' north-east-down and
# forward-right-down (both swaps are their own inverses)
_NED_R_ENU = ENU_R_SITE
_FLU_R_FRD = BODY_R_ROVER
COLUMNS = ["stop", "time_s", "site", "drive", "x_east_m", "y_north_m", "z_up_m", "easting", "northing",
           "planetocentric_latitude", "planetodetic_latitude", "longitude", "elevation", "roll", "pitch", "yaw",
           "sigma_major_m", "sigma_minor_m", "sigma_major_azimuth", "sigma_up_m"]


@dataclass(frozen=True)
class Localization:
    """One configuration's localization product, a row a stop (angles in degrees: yaw clockwise
    from north, pitch nose up, roll right side down; elevation above the body's reference surface;
    the ellipse's azimuth clockwise from north)."""

    name: str
    origin: LocalFrame
    map_crs_name: str
    stops: np.ndarray  # (N,) int
    times_s: np.ndarray
    site_drive: np.ndarray  # (N, 2) int
    enu: np.ndarray  # (N, 3)
    map_xy: np.ndarray  # (N, 2)
    geodetic: np.ndarray  # (N, 3) planetocentric latitude, east longitude, height
    vertical_latitude: np.ndarray  # (N,) planetodetic (planetographic) latitude
    ypr_deg: np.ndarray  # (N, 3) yaw, pitch, roll
    ellipse: np.ndarray  # (N, 4) major, minor (m), major's azimuth (deg), up (m)

    def rows(self) -> list[tuple]:
        return [(int(k), f"{t:.6f}", int(sd[0]), int(sd[1]), *(f"{v:.4f}" for v in e), *(f"{v:.4f}" for v in xy),
                 f"{g[0]:.10f}", f"{lat:.10f}", f"{g[1]:.10f}", f"{g[2]:.4f}",
                 *(f"{v:.5f}" for v in ypr[::-1]), *(f"{v:.4f}" for v in ell))
                for k, t, sd, e, xy, g, lat, ypr, ell in zip(self.stops, self.times_s, self.site_drive, self.enu,
                                                             self.map_xy, self.geodetic, self.vertical_latitude,
                                                             self.ypr_deg, self.ellipse, strict=True)]


def horizontal_ellipse(covariance: np.ndarray) -> np.ndarray:
    """(N, 4): 1-sigma semi-major and semi-minor axes (m), the major's azimuth clockwise from
    north (deg, 0-180), and the vertical sigma (m), of ENU position covariances (N, 3, 3)."""
    values, vectors = np.linalg.eigh(covariance[:, :2, :2])  # ascending
    major = vectors[:, :, 1]
    azimuth = np.degrees(np.arctan2(major[:, 0], major[:, 1])) % 180.0
    sigmas = np.sqrt(np.clip(values, 0.0, None))
    return np.column_stack([sigmas[:, 1], sigmas[:, 0], azimuth, np.sqrt(np.clip(covariance[:, 2, 2], 0.0, None))])


def localization(name: str, origin: LocalFrame, times_s: np.ndarray, world_T_body: np.ndarray,
                 position_covariance: np.ndarray, site_drive: np.ndarray) -> Localization:
    from scipy.spatial.transform import Rotation

    enu = world_T_body[:, :3, 3]
    ned_R_frd = _NED_R_ENU @ world_T_body[:, :3, :3] @ _FLU_R_FRD
    crs = origin.map_crs()
    ypr = Rotation.from_matrix(ned_R_frd).as_euler("ZYX", degrees=True)
    ypr[:, 0] %= 360.0
    return Localization(name, origin, crs.name, np.arange(len(enu)), np.asarray(times_s, float),
                        np.asarray(site_drive, int), enu, origin.to_map(enu, crs), origin.to_geodetic(enu),
                        origin.vertical_latitude_deg(enu), ypr, horizontal_ellipse(position_covariance))


def _wkb_point(lon: float, lat: float, h: float) -> bytes:
    return struct.pack("<BIddd", 1, 1001, lon, lat, h)  # ISO WKB Point Z


def _wkb_line(lon_lat_h: np.ndarray) -> bytes:
    return struct.pack("<BII", 1, 1002, len(lon_lat_h)) + np.ascontiguousarray(lon_lat_h, "<f8").tobytes()


def write_localization(folder: Path, product: Localization) -> list[Path]:
    """`localization_<name>.csv`, `.gpkg` (layers `stops` and `track`) and `.geojson`; the paths."""
    from pyogrio.raw import write

    stem = folder / f"localization_{product.name}"
    write_csv(stem.with_suffix(".csv"), COLUMNS, product.rows())
    lon_lat_h = product.geodetic[:, [1, 0, 2]]
    fields = [product.stops, product.times_s, product.site_drive[:, 0], product.site_drive[:, 1],
              *product.enu.T, *product.map_xy.T, product.geodetic[:, 0], product.vertical_latitude,
              product.geodetic[:, 1], product.geodetic[:, 2], *product.ypr_deg[:, ::-1].T, *product.ellipse.T]
    crs = product.origin.geographic_crs().to_wkt()
    gpkg = stem.with_suffix(".gpkg")
    try:
        write(gpkg, np.array([_wkb_point(*p) for p in lon_lat_h], dtype=object), fields, COLUMNS, layer="stops",
              driver="GPKG", geometry_type="Point Z", crs=crs)
        write(gpkg, np.array([_wkb_line(lon_lat_h)], dtype=object),
              [np.array([product.name]), np.array([product.map_crs_name])], ["config", "map_crs"], layer="track",
              driver="GPKG", geometry_type="LineString Z", crs=crs, append=True)
    except Exception as exc:  # noqa: BLE001  GDAL's errors come through pyogrio as several types
        raise WriteFailed(f"{gpkg}: the GeoPackage could not be written: {exc}") from None
    features = [{"type": "Feature", "properties": {"config": product.name, "crs": product.origin.geographic_crs().name,
                                                   "map_crs": product.map_crs_name},
                 "geometry": {"type": "LineString", "coordinates": np.round(lon_lat_h, 10).tolist()}}]
    features += [{"type": "Feature", "properties": {c: np.asarray(f)[i].item() for c, f in zip(COLUMNS, fields,
                                                                                                strict=True)},
                  "geometry": {"type": "Point", "coordinates": [round(float(v), 10) for v in p]}}
                 for i, p in enumerate(lon_lat_h)]
    geojson = stem.with_suffix(".geojson")
    geojson.write_text(json.dumps({"type": "FeatureCollection", "features": features}) + "\n", encoding="utf-8")
    return [stem.with_suffix(".csv"), gpkg, geojson]
