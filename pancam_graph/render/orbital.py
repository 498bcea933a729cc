"""Orbital products of a scenario's terrain: the DTM an orbiter's stereo would give of the site,
sampled on the map projection's grid (geodesy.LocalFrame.map_crs)."""

from __future__ import annotations

import numpy as np

from ..geodesy import LocalFrame
from ..records import MapRaster
from .terrain import Ground


def terrain_dtm(ground: Ground, frame: LocalFrame, centre_enu: np.ndarray, size_m: float,
                post_m: float = 1.0) -> MapRaster:
    """A DTM of the terrain around `centre_enu` (east, north), `size_m` on a side, one post every
    `post_m` of map coordinates: each post's map point taken to ENU and the terrain's height
    there. Heights are the local frame's up plus the origin's height (above the body's surface,
    to the curvature's drop across the map, a few millimetres over a kilometre)."""
    crs = frame.map_crs()
    corner = frame.to_map(np.array([[centre_enu[0] - size_m / 2, centre_enu[1] + size_m / 2, 0.0]]), crs)[0]
    x0, y0 = np.floor(corner[0] / post_m) * post_m, np.ceil(corner[1] / post_m) * post_m
    count = int(np.ceil(size_m / post_m))
    raster = MapRaster(np.zeros((count, count), np.float32), float(x0), float(y0), float(post_m), crs.to_wkt())
    x, y = raster.centres()
    gx, gy = np.meshgrid(x, y)
    enu = frame.from_map(np.column_stack([gx.ravel(), gy.ravel()]), frame.h0_m, crs)
    height, _, _ = ground.at(enu[:, :2])
    values = (height + frame.h0_m).reshape(count, count).astype(np.float32)
    return MapRaster(values, raster.x0_m, raster.y0_m, raster.post_m, raster.crs_wkt)
