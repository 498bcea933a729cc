"""Orbital products of a simulated world: the DTM an orbiter's stereo would give of the site,
sampled on the map projection's grid (geodesy.LocalFrame.map_crs) from the terrain's height
function (sim.world.LandmarkTerrain at measurement level, render.terrain.Ground when rendered)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geodesy import LocalFrame
from ..records import MapRaster


def terrain_dtm(height: Callable[[np.ndarray], np.ndarray], frame: LocalFrame, centre_enu: np.ndarray,
                size_m: float, post_m: float = 1.0) -> MapRaster:
    """A DTM of the terrain around `centre_enu` (east, north), `size_m` on a side, one post every
    `post_m` of map coordinates: each post's map point taken to ENU and `height` (the local
    frame's up at (N, 2) east-north points) there, plus the origin's height: heights above the
    body's surface, to the curvature's drop across the map (a few millimetres over a kilometre)."""
    crs = frame.map_crs()
    corner = frame.to_map(np.array([[centre_enu[0] - size_m / 2, centre_enu[1] + size_m / 2, 0.0]]), crs)[0]
    x0, y0 = np.floor(corner[0] / post_m) * post_m, np.ceil(corner[1] / post_m) * post_m
    count = int(np.ceil(size_m / post_m))
    dtm = MapRaster(np.empty((count, count), np.float32), float(x0), float(y0), float(post_m), crs.to_wkt())
    gx, gy = np.meshgrid(*dtm.centres())
    enu = frame.from_map(np.column_stack([gx.ravel(), gy.ravel()]), frame.h0_m, crs)
    dtm.values[:] = (height(enu[:, :2]) + frame.h0_m).reshape(count, count)
    return dtm
