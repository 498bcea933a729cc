"""Geodetic coordinates <-> local ENU at a geodetic origin, on Earth (WGS84) or Mars (the IAU 2015
sphere for positions, its ellipsoid for "up"), the local vertical anywhere in that frame, and the
map projection an orbital or survey map of the site would use; all through pyproj."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pyproj import CRS, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info
from pyproj.enums import TransformDirection
from pyproj.exceptions import ProjError

from ..errors import GeodesyError

Body = Literal["earth", "mars"]
MARS_RADIUS_M = 3_396_190.0  # the IAU 2015 Mars sphere (IAU_2015:49900), HiRISE's and CTX's datum
# Each body's geographic CRS, and the map projection of a site's orbital products on Mars:
# equirectangular on the sphere (IAU_2015:49910) with its standard parallel at the site, as HiRISE
# DTMs are, so that a map's pixels are square on the ground.
_GEOGRAPHIC = {"earth": "EPSG:4326", "mars": "IAU_2015:49900"}
_MARS_MAP = "IAU_2015:49910"
_STANDARD_PARALLEL = "8823"  # EPSG's parameter code: latitude of the 1st standard parallel
_SHAPE = {"earth": "+ellps=WGS84", "mars": f"+R={MARS_RADIUS_M!r}"}
# The surface whose normal is "up" (gravity, an accelerometer's tilt, a mission's site frame): on
# Mars the IAU 2015 ellipsoid (3,396.19 / 3,376.20 km), whose normal is the planetographic
# vertical, 0.05 deg from the sphere's at Gale and 0.2 deg at Jezero.
_UP_CRS = {"earth": "EPSG:4326", "mars": "IAU_2015:49901"}


def _shape_of(crs: str) -> str:
    ellipsoid = CRS.from_user_input(crs).ellipsoid
    return f"+a={ellipsoid.semi_major_metre!r} +b={ellipsoid.semi_minor_metre!r}"


@dataclass(frozen=True)
class LocalFrame:
    """Local east-north-up frame at (lat0, lon0, h0), its up the body's vertical there.

    Positions are on the body's reference surface: the WGS84 ellipsoid on Earth, the IAU 2015
    sphere on Mars (planetocentric latitude, east longitude), heights above it. "Up" is the
    normal of the body's ellipsoid through the origin (WGS84; the IAU 2015 Mars ellipsoid, i.e.
    the planetographic vertical), as gravity and a mission's site frame have it. Uses
    `+proj=cart` then `+proj=topocentric`: exact, no flat-earth shortcut. The frame is Cartesian:
    away from the origin the vertical turns by the distance over the body's radius (`up_at`).
    """

    lat0_deg: float
    lon0_deg: float
    h0_m: float
    body: Body = "earth"
    _transformer: Transformer = field(init=False, repr=False, compare=False)
    _to_up: Transformer = field(init=False, repr=False, compare=False)  # body geodetic -> up-ellipsoid geodetic
    up_lat_deg: float = field(init=False, repr=False, compare=False)  # the origin's vertical's latitude

    def __post_init__(self) -> None:
        # Plain floats: a numpy scalar's repr ("np.float64(49.0)") would corrupt the PROJ string,
        # and PROJ then silently builds a different transformation.
        for name in ("lat0_deg", "lon0_deg", "h0_m"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not (-90.0 <= self.lat0_deg <= 90.0) or not (-180.0 <= self.lon0_deg <= 360.0):
            raise GeodesyError(f"origin out of range: lat {self.lat0_deg}, lon {self.lon0_deg}")
        if self.body not in _SHAPE:
            raise GeodesyError(f"body {self.body!r}: expected {' or '.join(_SHAPE)}")
        shape = up_shape = _SHAPE[self.body]
        if _UP_CRS[self.body] == _GEOGRAPHIC[self.body]:  # Earth: positions are on the up ellipsoid
            to_up = Transformer.from_pipeline("+proj=noop")
            lon, lat, h = self.lon0_deg, self.lat0_deg, self.h0_m
        else:  # the origin on the up ellipsoid: the same point, its latitude that of the normal through it
            up_shape = _shape_of(_UP_CRS[self.body])
            to_up = Transformer.from_pipeline(f"+proj=pipeline +step +proj=cart {shape} +step +inv +proj=cart "
                                              f"{up_shape}")
            lon, lat, h = to_up.transform(self.lon0_deg, self.lat0_deg, self.h0_m, errcheck=True)
        pipeline = (
            f"+proj=pipeline +step +proj=cart {shape} "
            f"+step +proj=topocentric {up_shape} +lat_0={float(lat)!r} +lon_0={float(lon)!r} +h_0={float(h)!r}"
        )
        object.__setattr__(self, "_transformer", Transformer.from_pipeline(pipeline))
        object.__setattr__(self, "_to_up", to_up)
        object.__setattr__(self, "up_lat_deg", float(lat))

    def enu_R_fixed(self) -> np.ndarray:
        """3x3 rotation of a body-fixed Cartesian direction (x to longitude 0 on the equator, z
        to the north pole) into this frame."""
        return _enu_R_fixed(np.deg2rad(self.up_lat_deg), np.deg2rad(self.lon0_deg))

    def up_at(self, enu: np.ndarray) -> np.ndarray:
        """(N, 3) unit vectors of the vertical (the up ellipsoid's normal) at ENU points (N, 3),
        in this frame: (0, 0, 1) at the origin, turned by about distance / radius away from it."""
        geodetic = self.to_geodetic(enu)
        lat, lon = np.deg2rad(self._vertical_latitude(geodetic)), np.deg2rad(geodetic[:, 1])
        normal = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
        return normal @ self.enu_R_fixed().T

    def vertical_latitude_deg(self, enu: np.ndarray) -> np.ndarray:
        """(N,) latitude of the vertical (the up ellipsoid's normal) at ENU points (N, 3): the
        planetographic latitude on Mars, the geodetic one on Earth."""
        return self._vertical_latitude(self.to_geodetic(enu))

    def _vertical_latitude(self, geodetic: np.ndarray) -> np.ndarray:
        try:
            _, lat, _ = self._to_up.transform(geodetic[:, 1], geodetic[:, 0], geodetic[:, 2], errcheck=True)
        except ProjError as exc:
            raise GeodesyError(f"the vertical at ENU points failed: {exc}") from exc
        return np.asarray(lat, dtype=float)

    def geographic_crs(self) -> CRS:
        """The body's geographic CRS the positions are on (WGS84; the IAU 2015 Mars sphere,
        planetocentric)."""
        return CRS.from_user_input(_GEOGRAPHIC[self.body])

    def map_crs(self) -> CRS:
        """The projected CRS of a map of this site: on Earth the UTM zone of the origin, on Mars
        the equirectangular projection of the IAU 2015 sphere (metres) with its standard parallel
        at the origin's latitude."""
        if self.body == "mars":
            definition = CRS.from_user_input(_MARS_MAP).to_json_dict()
            for parameter in definition["conversion"]["parameters"]:
                if str(parameter["id"]["code"]) == _STANDARD_PARALLEL:
                    parameter["value"] = self.lat0_deg
            definition.pop("id")
            definition["name"] = f"Mars (2015) - Sphere / Ocentric / Equirectangular, clat = {self.lat0_deg:g}"
            definition["conversion"]["name"] = f"Equirectangular, clat = {self.lat0_deg:g}"
            return CRS.from_json_dict(definition)
        lon = (self.lon0_deg + 180.0) % 360.0 - 180.0
        zones = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, self.lat0_deg, lon,
                                                                                         self.lat0_deg))
        if not zones:
            raise GeodesyError(f"no UTM zone at lat {self.lat0_deg}, lon {self.lon0_deg}")
        return CRS.from_epsg(int(zones[0].code))

    def to_map(self, enu: np.ndarray, crs: CRS | None = None) -> np.ndarray:
        """(N, 2) map coordinates (easting, northing in metres of `crs`, default `map_crs()`) of
        ENU points (N, 3)."""
        geodetic = self.to_geodetic(enu)
        try:
            to_map = Transformer.from_crs(_GEOGRAPHIC[self.body], crs or self.map_crs(), always_xy=True)
            x, y = to_map.transform(geodetic[:, 1], geodetic[:, 0], errcheck=True)
        except ProjError as exc:
            raise GeodesyError(f"ENU -> map coordinates failed: {exc}") from exc
        return np.column_stack([x, y])

    def from_map(self, xy: np.ndarray, h_m: np.ndarray | float = 0.0, crs: CRS | None = None) -> np.ndarray:
        """ENU points (N, 3) of map coordinates (N, 2) at heights `h_m` above the body's surface."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        try:
            from_map = Transformer.from_crs(crs or self.map_crs(), _GEOGRAPHIC[self.body], always_xy=True)
            lon, lat = from_map.transform(xy[:, 0], xy[:, 1], errcheck=True)
        except ProjError as exc:
            raise GeodesyError(f"map coordinates -> ENU failed: {exc}") from exc
        return self.to_enu(lat, lon, np.broadcast_to(np.asarray(h_m, dtype=float), lat.shape))

    def to_enu(self, lat_deg, lon_deg, h_m) -> np.ndarray:
        """ENU (N, 3) in metres of geodetic points (degrees, ellipsoidal metres)."""
        lat, lon, h = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (lat_deg, lon_deg, h_m))
        if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon)) and np.all(np.isfinite(h))):
            raise GeodesyError("non-finite latitude, longitude or height")
        if np.any(np.abs(lat) > 90.0):
            raise GeodesyError(f"latitude out of range [-90, 90]: {lat[np.abs(lat) > 90][0]}")
        try:
            e, n, u = self._transformer.transform(lon, lat, h, errcheck=True)
        except ProjError as exc:
            raise GeodesyError(f"geodetic -> ENU failed: {exc}") from exc
        return np.column_stack([e, n, u])

    def to_geodetic(self, enu: np.ndarray) -> np.ndarray:
        """(lat_deg, lon_deg, h_m) rows (N, 3) of ENU points (N, 3)."""
        enu = np.atleast_2d(np.asarray(enu, dtype=float))
        if not np.all(np.isfinite(enu)):
            raise GeodesyError("non-finite ENU coordinates")
        try:
            lon, lat, h = self._transformer.transform(
                enu[:, 0], enu[:, 1], enu[:, 2], direction=TransformDirection.INVERSE, errcheck=True
            )
        except ProjError as exc:
            raise GeodesyError(f"ENU -> geodetic failed: {exc}") from exc
        return np.column_stack([lat, lon, h])


def _enu_R_fixed(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Body-fixed Cartesian -> east, north, up at a geodetic latitude and longitude."""
    sin_lat, cos_lat, sin_lon, cos_lon = np.sin(lat_rad), np.cos(lat_rad), np.sin(lon_rad), np.cos(lon_rad)
    return np.array([[-sin_lon, cos_lon, 0.0],
                     [-sin_lat * cos_lon, -sin_lat * sin_lon, cos_lat],
                     [cos_lat * cos_lon, cos_lat * sin_lon, sin_lat]])
