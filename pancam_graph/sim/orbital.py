"""Orbital products of a simulated world: the DTM an orbiter's stereo would give of the site,
sampled on the map projection's grid (maps.sampled_raster) from the terrain's height function
(sim.world.LandmarkTerrain at measurement level, render.terrain.Ground when rendered)."""

from __future__ import annotations

import numpy as np

from ..geodesy import LocalFrame
from ..maps import Height, sampled_raster
from ..records import MapRaster


def terrain_dtm(height: Height, frame: LocalFrame, centre_enu: np.ndarray, size_m: float,
                post_m: float = 1.0) -> MapRaster:
    """A DTM of the terrain around `centre_enu` (east, north), `size_m` on a side, one post every
    `post_m` of map coordinates."""
    half = np.array([size_m / 2, size_m / 2])
    return sampled_raster(height, frame, np.asarray(centre_enu[:2]) - half, np.asarray(centre_enu[:2]) + half,
                          post_m)
