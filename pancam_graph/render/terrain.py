"""The rendered world's terrain: a height field around the scenario's path, in tiles.

The rover drives on the path's own elevation (the simulated poses), so the terrain blends from
the path's height on the path to undulating ground a few metres away. Each vertex carries a
texture contrast: 1 on ordinary ground, the scenario's featureless factor along its
featureless stretches (a sand sheet the front-end should find nothing on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import Scenario
from ..sim.world import DensePath

GRID_M = 0.5  # height-field spacing
TILE_M = 40.0  # terrain is drawn tile by tile: only tiles near the camera
_PATH_FLAT_M = (2.0, 8.0)  # the ground is the path's own height within 2 m, undulating beyond 8 m


@dataclass(frozen=True)
class TerrainTile:
    centre: np.ndarray  # (2,) east, north
    vertices: np.ndarray  # (N, 4) float32: east, north, up, texture contrast
    triangles: np.ndarray  # (M, 3) uint32


def undulation(xy: np.ndarray, amplitude_m: float, seed: int) -> np.ndarray:
    """Smooth relief at several scales (metres), the same for every seed's geometry family."""
    phase = np.random.default_rng([seed, 7]).uniform(0, 2 * np.pi, size=6)
    x, y = xy[:, 0], xy[:, 1]
    return amplitude_m * 0.5 * (np.sin(x / 23.0 + phase[0]) * np.cos(y / 31.0 + phase[1])
                                + np.sin(x / 11.0 + phase[2]) * np.sin(y / 13.0 + phase[3])
                                + 0.3 * np.sin(x / 3.7 + phase[4]) * np.sin(y / 4.3 + phase[5]))


def terrain_tiles(scenario: Scenario, path: DensePath, seed: int) -> list[TerrainTile]:
    """Height-field tiles covering the corridor around the path."""
    w = scenario.terrain.corridor_half_width_m
    lo = np.floor((path.points[:, :2].min(axis=0) - w) / TILE_M) * TILE_M
    hi = np.ceil((path.points[:, :2].max(axis=0) + w) / TILE_M) * TILE_M
    tree = cKDTree(path.points[:, :2])
    per_side = int(round(TILE_M / GRID_M)) + 1
    tiles = []
    for x0 in np.arange(lo[0], hi[0], TILE_M):
        for y0 in np.arange(lo[1], hi[1], TILE_M):
            gx, gy = np.meshgrid(np.linspace(x0, x0 + TILE_M, per_side), np.linspace(y0, y0 + TILE_M, per_side))
            xy = np.column_stack([gx.ravel(), gy.ravel()])
            dist, nearest = tree.query(xy)
            if dist.min() > w + TILE_M:
                continue
            blend = np.clip((dist - _PATH_FLAT_M[0]) / (_PATH_FLAT_M[1] - _PATH_FLAT_M[0]), 0.0, 1.0)
            z = path.points[nearest, 2] + blend * undulation(xy, scenario.terrain.undulation_m, seed)
            contrast = np.ones(len(xy))
            s_near = path.distance_m[nearest]
            for a, b in scenario.terrain.featureless:
                contrast[(s_near >= a) & (s_near <= b) & (dist < w)] = scenario.terrain.featureless_density_factor
            vertices = np.column_stack([xy, z, contrast]).astype(np.float32)
            i = np.arange(per_side - 1)
            a = (i[None, :] + per_side * i[:, None]).ravel()
            quads = np.column_stack([a, a + 1, a + per_side, a + 1, a + per_side + 1, a + per_side])
            tiles.append(TerrainTile(np.array([x0 + TILE_M / 2, y0 + TILE_M / 2]), vertices,
                                     quads.reshape(-1, 3).astype(np.uint32)))
    return tiles
