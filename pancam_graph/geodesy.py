"""WGS84 geodetic coordinates <-> local ENU at a geodetic origin, through pyproj."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import Transformer
from pyproj.enums import TransformDirection
from pyproj.exceptions import ProjError

from .errors import GeodesyError


@dataclass(frozen=True)
class LocalFrame:
    """Local east-north-up frame tangent to the WGS84 ellipsoid at (lat0, lon0, h0).

    Heights are ellipsoidal. Uses `+proj=cart` then `+proj=topocentric`: exact, no
    flat-earth shortcut.
    """

    lat0_deg: float
    lon0_deg: float
    h0_m: float
    _transformer: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Plain floats: a numpy scalar's repr ("np.float64(49.0)") would corrupt the PROJ string,
        # and PROJ then silently builds a different transformation.
        for name in ("lat0_deg", "lon0_deg", "h0_m"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not (-90.0 <= self.lat0_deg <= 90.0) or not (-180.0 <= self.lon0_deg <= 360.0):
            raise GeodesyError(f"origin out of range: lat {self.lat0_deg}, lon {self.lon0_deg}")
        pipeline = (
            "+proj=pipeline +step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={self.lat0_deg!r} "
            f"+lon_0={self.lon0_deg!r} +h_0={self.h0_m!r}"
        )
        object.__setattr__(self, "_transformer", Transformer.from_pipeline(pipeline))

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
