"""The simulated world: a smoothed path with elevation, true rover poses at stops, sites,
and a seeded landmark field on undulating terrain around the path."""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..config import PathConfig, SitesConfig, TerrainConfig

_DENSE_STEP_M = 0.25
CRATER_MARGIN_M = 150.0  # craters reach this far beyond the landmark corridor's box (an orbital map's margin)


@dataclass(frozen=True)
class DensePath:
    """The path sampled every 0.25 m: positions (N, 3) and cumulative distance (N,)."""

    points: np.ndarray
    distance_m: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.distance_m[-1])

    def at(self, s: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(s, self.distance_m, self.points[:, i]) for i in range(3)])


def _chaikin(points: np.ndarray, keep: set[int], iterations: int = 3) -> np.ndarray:
    """Chaikin corner cutting that rounds every vertex except the end points and `keep`."""
    pts = np.asarray(points, dtype=float)
    fixed = {0, len(pts) - 1} | keep
    for _ in range(iterations):
        out, out_fixed = [pts[0]], {0}
        for i in range(len(pts) - 1):
            a, b = pts[i], pts[i + 1]
            if i not in fixed:
                out.append(0.75 * a + 0.25 * b)
            if i + 1 in fixed:
                out_fixed.add(len(out))
                out.append(b)
            else:
                out.append(0.25 * a + 0.75 * b)
        pts, fixed = np.array(out), out_fixed
    return pts


def dense_path(cfg: PathConfig) -> DensePath:
    way = np.asarray(cfg.waypoints, dtype=float)
    smooth = _chaikin(way, set(cfg.sharp_turns))
    seg = np.linalg.norm(np.diff(smooth, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(s[-1] / _DENSE_STEP_M) + 1, 2)
    grid = np.linspace(0.0, s[-1], n)
    pts = np.column_stack([np.interp(grid, s, smooth[:, i]) for i in range(3)])
    # A dense polyline keeps sharp corners sharp and gentle ones smooth.
    return DensePath(points=pts, distance_m=grid)


def stop_distances(path: DensePath, cfg: PathConfig, rng: np.random.Generator) -> np.ndarray:
    lo, hi = cfg.stop_spacing_m
    steps = rng.uniform(lo, hi, size=int(path.length_m / lo) + 2)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    return s[s <= path.length_m]


def site_stops(stop_s: np.ndarray, cfg: SitesConfig, rng: np.random.Generator) -> list[int]:
    """Stop indices of sites: the first stop, then every 30-60 m (configurable) of path."""
    sites = [0]
    next_s = rng.uniform(*cfg.spacing_m)
    for k, s in enumerate(stop_s):
        if s >= next_s:
            sites.append(k)
            next_s = s + rng.uniform(*cfg.spacing_m)
    return sites


def rover_poses(path: DensePath, stop_s: np.ndarray) -> np.ndarray:
    """world_T_body (N, 4, 4): heading along the path, pitch from its slope, gentle roll."""
    look = 0.5  # m either side for the tangent; small enough to keep sharp corners sharp
    ahead = path.at(np.minimum(stop_s + look, path.length_m))
    behind = path.at(np.maximum(stop_s - look, 0.0))
    here = path.at(stop_s)
    # At a corner the rover faces the leg it is about to drive.
    forward = np.where((stop_s + look <= path.length_m)[:, None], ahead - here, here - behind)
    poses = np.zeros((len(stop_s), 4, 4))
    for k, (p, d) in enumerate(zip(here, forward, strict=True)):
        yaw = np.arctan2(d[1], d[0])
        pitch = np.arctan2(d[2], np.hypot(d[0], d[1]))
        roll = 0.03 * np.sin(stop_s[k] / 17.0)
        rot = gtsam.Rot3.Ypr(yaw, -pitch, roll)  # body y is left: nose-up is a negative y rotation
        poses[k] = gtsam.Pose3(rot, p).matrix()
    return poses


@dataclass(frozen=True)
class Craters:
    """Simple impact craters: a bowl 0.2 radii deep inside the rim, a raised rim 0.05 radii high
    falling off as (R/r)^3 outside it, nothing beyond two radii."""

    centres: np.ndarray  # (K, 2) east, north
    radii: np.ndarray  # (K,)

    @classmethod
    def drawn(cls, lo: np.ndarray, hi: np.ndarray, per_km2: float, radius_m: tuple[float, float],
              rng: np.random.Generator) -> Craters:
        """Craters uniformly over the box lo..hi (east, north), radii from a -2 cumulative power law
        (Mars' small craters) between radius_m's bounds."""
        count = rng.poisson(per_km2 * float(np.prod(hi - lo)) / 1e6)
        centres = rng.uniform(lo, hi, size=(count, 2))
        a, b = np.asarray(radius_m, dtype=float) ** -2.0
        radii = (a - rng.random(count) * (a - b)) ** -0.5
        return cls(centres, radii)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """The craters' relief (m) at (N, 2) east-north positions."""
        out = np.zeros(len(xy))
        if not len(self.radii) or not len(xy):
            return out
        points = cKDTree(xy)
        for centre, radius in zip(self.centres, self.radii, strict=True):
            near = np.asarray(points.query_ball_point(centre, 2.0 * radius), dtype=int)
            if not len(near):
                continue
            r = np.linalg.norm(xy[near] - centre, axis=1) / radius
            rim = 0.05 * radius
            out[near] += np.where(r < 1.0, 0.2 * radius * (r**2 - 1.0) + rim,
                                  rim * (np.maximum(r, 1.0) ** -3.0 - 0.125) / 0.875)
        return out


@dataclass(frozen=True)
class LandmarkTerrain:
    """The ground the simulated landmarks lie on: the path's own elevation at its nearest point plus
    smooth undulation at 11-31 m wavelengths and, where the scenario has them, craters. Each
    landmark adds the terrain's roughness on top (rocks and the like), which an orbital DTM at
    1 m posts does not resolve."""

    path: DensePath
    undulation_m: float
    phase: np.ndarray  # (4,) rad
    craters: Craters | None = None
    tree: cKDTree | None = field(default=None, repr=False, compare=False)  # the path's east-north (built if None)

    def __post_init__(self) -> None:
        if self.tree is None:
            object.__setattr__(self, "tree", cKDTree(self.path.points[:, :2]))

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Elevation (m, up of the local frame) at (N, 2) east-north positions."""
        xy = np.atleast_2d(xy)
        _, nearest = self.tree.query(xy)
        ground = self.path.points[nearest, 2] + self.undulation_m * 0.5 * (
            np.sin(xy[:, 0] / 23.0 + self.phase[0]) * np.cos(xy[:, 1] / 31.0 + self.phase[1])
            + np.sin(xy[:, 0] / 11.0 + self.phase[2]) * np.sin(xy[:, 1] / 13.0 + self.phase[3])
        )
        return ground if self.craters is None else ground + self.craters.height(xy)


def landmark_field(path: DensePath, cfg: TerrainConfig, rng: np.random.Generator,
                   crater_rng: np.random.Generator | None = None) -> tuple[np.ndarray, LandmarkTerrain]:
    """Landmarks (M, 3) uniformly in a corridor around the path, on undulating terrain (returned
    too) with the terrain's roughness; thinned to nearly nothing along the featureless stretches.
    Craters, when the terrain has them, are drawn from `crater_rng` (a stream of their own, so
    that a terrain without them is the same as before they existed) over the corridor's box and
    CRATER_MARGIN_M around it, where an orbital map of the traverse reaches."""
    w = cfg.corridor_half_width_m
    lo = path.points[:, :2].min(axis=0) - w
    hi = path.points[:, :2].max(axis=0) + w
    area = float(np.prod(hi - lo))
    xy = rng.uniform(lo, hi, size=(rng.poisson(cfg.landmark_density_per_m2 * area), 2))
    tree = cKDTree(path.points[:, :2])
    dist, nearest = tree.query(xy)
    keep = dist <= w
    s_near = path.distance_m[nearest]
    for a, b in cfg.featureless:
        in_gap = (s_near >= a) & (s_near <= b)
        keep &= ~in_gap | (rng.random(len(xy)) < cfg.featureless_density_factor)
    xy = xy[keep]
    craters = None
    if cfg.craters_per_km2 > 0:
        craters = Craters.drawn(lo - CRATER_MARGIN_M, hi + CRATER_MARGIN_M, cfg.craters_per_km2, cfg.crater_radius_m,
                                crater_rng if crater_rng is not None else np.random.default_rng())
    terrain = LandmarkTerrain(path, cfg.undulation_m, rng.uniform(0, 2 * np.pi, size=4), tree=tree,
                              craters=craters)
    z = terrain.height(xy) + rng.normal(0.0, cfg.roughness_m, len(xy))
    return np.column_stack([xy, z]), terrain
