"""The rendered world's terrain: a height field around the scenario's path, in tiles, with rocks.

The rover drives on the path's own elevation (the simulated poses), so the terrain blends from
the path's height on the path to undulating ground a few metres away. Each vertex carries a
texture contrast: 1 on ordinary ground, the scenario's featureless factor along its
featureless stretches (a sand sheet the front-end should find nothing on). A scenario with
craters (`[terrain] craters_per_km2`) has the same craters as its measurement-level simulation
(sim.world.Craters, drawn from the same stream over the same box), flattened on the path as
the rest of the relief is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import Scenario
from ..sim.world import CRATER_MARGIN_M, Craters, DensePath

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


class Ground:
    """The terrain's height and texture contrast at any horizontal position."""

    def __init__(self, scenario: Scenario, path: DensePath, seed: int):
        self.scenario, self.path, self.seed = scenario, path, seed
        self.tree = cKDTree(path.points[:, :2])
        terrain = scenario.terrain
        self.craters = None
        if terrain.craters_per_km2 > 0:
            w = terrain.corridor_half_width_m
            lo, hi = path.points[:, :2].min(axis=0) - w, path.points[:, :2].max(axis=0) + w
            self.craters = Craters.drawn(lo - CRATER_MARGIN_M, hi + CRATER_MARGIN_M, terrain.craters_per_km2,
                                         terrain.crater_radius_m, np.random.default_rng([seed, 3]))

    def at(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, texture contrast, distance to the path m) at (N, 2) positions."""
        dist, nearest = self.tree.query(xy)
        blend = np.clip((dist - _PATH_FLAT_M[0]) / (_PATH_FLAT_M[1] - _PATH_FLAT_M[0]), 0.0, 1.0)
        relief = undulation(xy, self.scenario.terrain.undulation_m, self.seed)
        if self.craters is not None:
            relief = relief + self.craters.height(xy)
        z = self.path.points[nearest, 2] + blend * relief
        contrast = np.ones(len(xy))
        s_near = self.path.distance_m[nearest]
        w = self.scenario.terrain.corridor_half_width_m
        for a, b in self.scenario.terrain.featureless:
            contrast[(s_near >= a) & (s_near <= b) & (dist < w)] = self.scenario.terrain.featureless_density_factor
        return z, contrast, dist

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Elevation (m) at (N, 2) positions: the terrain as an orbiter sees it (maps.Height)."""
        return self.at(np.atleast_2d(xy))[0]


def terrain_tiles(scenario: Scenario, path: DensePath, seed: int) -> list[TerrainTile]:
    """Height-field tiles covering the corridor around the path, with the rocks on them."""
    ground = Ground(scenario, path, seed)
    w = scenario.terrain.corridor_half_width_m
    lo = np.floor((path.points[:, :2].min(axis=0) - w) / TILE_M) * TILE_M
    hi = np.ceil((path.points[:, :2].max(axis=0) + w) / TILE_M) * TILE_M
    per_side = int(round(TILE_M / GRID_M)) + 1
    i = np.arange(per_side - 1)
    a = (i[None, :] + per_side * i[:, None]).ravel()
    quads = np.column_stack([a, a + 1, a + per_side, a + 1, a + per_side + 1, a + per_side]).reshape(-1, 3)
    rng = np.random.default_rng([seed, 11])
    tiles = []
    for x0 in np.arange(lo[0], hi[0], TILE_M):
        for y0 in np.arange(lo[1], hi[1], TILE_M):
            gx, gy = np.meshgrid(np.linspace(x0, x0 + TILE_M, per_side), np.linspace(y0, y0 + TILE_M, per_side))
            xy = np.column_stack([gx.ravel(), gy.ravel()])
            z, contrast, dist = ground.at(xy)
            if dist.min() > w + TILE_M:
                continue
            vertices = [np.column_stack([xy, z, contrast])]
            triangles = [quads]
            for rock_vertices, rock_triangles in _rocks(ground, (x0, y0), scenario.render.rocks_per_100m2, rng):
                triangles.append(rock_triangles + sum(len(v) for v in vertices))
                vertices.append(rock_vertices)
            tiles.append(TerrainTile(np.array([x0 + TILE_M / 2, y0 + TILE_M / 2]),
                                     np.vstack(vertices).astype(np.float32), np.vstack(triangles).astype(np.uint32)))
    return tiles


_ROCK_CLEARANCE_M = 2.5  # no rock on the rover's path


def _rocks(ground: Ground, corner: tuple[float, float], per_100m2: float, rng: np.random.Generator):
    """(vertices, triangles) of the rocks of one tile: lumpy, half-buried ellipsoids 0.15-1 m
    across (more small than large ones), away from the path and off featureless ground."""
    count = rng.poisson(per_100m2 * TILE_M * TILE_M / 100.0)
    centres = np.asarray(corner) + rng.uniform(0.0, TILE_M, (count, 2))
    z, contrast, dist = ground.at(centres) if count else (np.zeros(0),) * 3
    sphere_vertices, sphere_triangles = _icosphere(2)
    for k in np.flatnonzero((dist > _ROCK_CLEARANCE_M) & (contrast >= 1.0)
                            & (dist < ground.scenario.terrain.corridor_half_width_m)):
        size = 0.15 * (1.0 - rng.uniform() * (1.0 - (0.15 / 1.0) ** 1.5)) ** (-1.0 / 1.5)  # Pareto, cut at 1 m
        axes = size / 2.0 * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.4, 0.8)])
        lumps = rng.normal(0.0, 1.0, (4, 3))
        bump = 1.0 + 0.12 * np.tanh(np.sin(sphere_vertices @ lumps.T * 2.5).sum(axis=1) / 2.0)
        yaw = rng.uniform(0.0, 2.0 * np.pi)
        turn = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        local = (sphere_vertices * bump[:, None] * axes) @ turn.T
        position = np.array([*centres[k], z[k] - 0.35 * axes[2]])  # a third buried
        rock_contrast = 2.0 + rng.uniform(0.0, 0.4)  # above 1.5 marks rock for the shader
        yield np.column_stack([local + position, np.full(len(local), rock_contrast)]), sphere_triangles


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere vertices and triangles from a subdivided icosahedron."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    vertices = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
                (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = [np.array(v, float) / np.linalg.norm(v) for v in vertices]
    middle: dict[tuple[int, int], int] = {}

    def midpoint(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in middle:
            m = points[i] + points[j]
            points.append(m / np.linalg.norm(m))
            middle[key] = len(points) - 1
        return middle[key]

    for _ in range(subdivisions):
        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
    return np.array(points), np.array(faces, dtype=np.int64)
