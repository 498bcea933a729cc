"""The rerun scene of a run: entity paths, the default blueprint and the archetypes, shared by
the live recorder and the replay of a results folder so both look the same.

Entities (world = local ENU, z up):
    world/terrain                     true landmark field (simulations only), static
    world/truth                       true trajectory, static
    world/gps                         GPS fixes in ENU (grey used, red flagged outlier)
    world/sites                       site markers; world/sites/panoramas: the latest site's frustums
    world/estimate/<config>/trajectory, /covariance (95 % ellipsoids), /landmarks, /ties
    world/estimate/<config>/trajectory/tail   live: the trajectory since its last refresh
    world/rover, world/rover/left_cam  current pose of the primary configuration, its left WAC
    world/rover/left_cam/features     the stop's stereo features (green: tracked from the last stop)
    map/gps, map/truth, map/estimate/<config>, map/rover   the same in WGS84 latitude/longitude
    world/orbital_map                 the orbital DTM as a mesh textured with its orthoimage, static
    orbital_map/image, orbital_map/truth, orbital_map/<config>   the orthoimage (the 2-D map's
                                      background) and the trajectories on it, in its pixels
    plots/<series>/<config>           time series
    events                            text log: VO bridges, sites, GPS outliers
Timelines: `stop` (index), `sensor_time` (the stop's time) and `distance_cm` (odometer:
the sum of the estimated motions, available live and for recorded data).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import gtsam
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera, Rig
from ..graph import chi2
from ..orbital.maps import post_enu
from ..records import OrbitalMap

APP_ID = "pancam_graph"
COLOURS = {  # the matplotlib tab10 colours of the report plots
    "dead_reckoning": (148, 103, 189),
    "vo": (214, 39, 40),
    "vo_sites": (255, 127, 14),
    "vo_sites_hrc": (44, 160, 44),
    "full": (31, 119, 180),
    "vo_sites_orbital": (140, 86, 75),
    "full_mars": (227, 119, 194),
}
TRUTH_COLOUR = (235, 235, 235)
TIE_ALPHA = 50  # tie links are many: faint, so the trajectories stay visible
GPS_COLOUR = (150, 150, 150)
OUTLIER_COLOUR = (230, 30, 30)
HELD_OUT_COLOUR = (60, 120, 230)  # fixes kept out of the graph for scoring
ELLIPSOID_SCALE_95 = float(np.sqrt(chi2.quantile(0.95, 3)))  # 95 % of a 3-D Gaussian
FRUSTUM_DEPTH_M = 0.6
TERRAIN_POINTS_SHOWN = 10_000  # about: the field's shape, drawn fast enough by a software renderer
SERIES = {  # entity under plots/ -> (title, per configuration)
    "error_m": ("position error vs truth (m)", True),
    "vo_inliers": ("VO inliers per stop", False),
    "isam2_update_ms": ("iSAM2 update (ms)", True),
    "relinearized": ("variables relinearized", True),
    "gps_outliers": ("GPS fixes flagged outlier (cumulative)", True),
}


def colour(config: str) -> tuple[int, int, int]:
    return COLOURS.get(config, (200, 200, 0))


def estimate_path(config: str, part: str) -> str:
    """A configuration's entity in the 3-D view; `part`: trajectory, trajectory/tail (live: the
    trajectory since its last refresh, rerun_live.py), covariance, landmarks or ties."""
    return f"world/estimate/{config}/{part}"


def map_path(config: str) -> str:
    return f"map/estimate/{config}"


def series_path(name: str, config: str | None = None) -> str:
    return f"plots/{name}" + (f"/{config}" if config else "")


def blueprint(configs: list[str], extent: np.ndarray | None = None, orbital_map: bool = False) -> rrb.Blueprint:
    """The 3-D traverse left; the error plot right, the other series in tabs beside it, and the
    camera and the map in tabs below; the stop timeline, following the data. A tab draws only
    when shown: a software-rendered browser keeps up, and the map (rerun's maps are online tiles)
    asks for nothing offline until it is opened. `extent` (points spanning the traverse, when
    known) places the 3-D eye above its south side. `orbital_map`: a tab with the orbital
    orthoimage under the trajectories."""
    plots = [rrb.TimeSeriesView(origin=series_path(name), name=title) for name, (title, _) in SERIES.items()]
    eye = None
    if extent is not None and len(extent):
        lo, hi = np.min(extent, axis=0), np.max(extent, axis=0)
        centre, radius = (lo + hi) / 2.0, max(float(np.max(hi - lo)) / 2.0, 10.0)
        eye = rrb.EyeControls3D(position=centre + np.array([0.0, -2.0 * radius, 1.8 * radius]),
                                look_target=centre, eye_up=[0.0, 0.0, 1.0])
    # Tie links hide by default (thousands of lines fanning out of every site bury the
    # trajectories), and so do the landmarks of the configurations other than the primary (last)
    # one: they nearly coincide with the primary's.
    hidden = ([f"- {estimate_path(c, 'ties')}" for c in configs]
              + [f"- {estimate_path(c, 'landmarks')}" for c in configs[:-1]])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="traverse (local ENU)", eye_controls=eye,
                              contents=["+ $origin/**", *hidden]),
            rrb.Vertical(
                rrb.Tabs(*plots, active_tab=0),
                rrb.Tabs(rrb.Spatial2DView(origin="world/rover/left_cam", name="left WAC features"),
                         *([rrb.Spatial2DView(origin="orbital_map", name="orbital map (orthoimage)")]
                           if orbital_map else []),
                         rrb.MapView(origin="map", name="map (WGS84, online tiles)"), active_tab=0),
                row_shares=[1, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="stop", play_state="following", state="collapsed"),
        collapse_panels=True,
    )


def set_stop_time(rec: rr.RecordingStream, stop: int, time_s: float, distance_m: float) -> None:
    rec.set_time("stop", sequence=stop)
    rec.set_time("distance_cm", sequence=int(round(distance_m * 100.0)))
    if time_s > 1e8:  # looks like UNIX time (recorded data)
        rec.set_time("sensor_time", timestamp=time_s)
    else:
        rec.set_time("sensor_time", duration=time_s)


def time_columns(stops, times_s, distances_m) -> list[rr.TimeColumn]:
    times_s = np.asarray(times_s, dtype=float)
    sensor = (rr.TimeColumn("sensor_time", timestamp=times_s) if len(times_s) and times_s[0] > 1e8
              else rr.TimeColumn("sensor_time", duration=times_s))
    return [
        rr.TimeColumn("stop", sequence=np.asarray(stops, dtype=np.int64)),
        rr.TimeColumn("distance_cm", sequence=np.round(np.asarray(distances_m) * 100.0).astype(np.int64)),
        sensor,
    ]


def log_static(
    rec: rr.RecordingStream,
    configs: list[str],
    rig: Rig,
    left_mount: np.ndarray,
    origin: LocalFrame,
    truth_positions: np.ndarray | None,
    truth_landmarks: np.ndarray | None,
) -> None:
    """Coordinates, calibration, series styles and the truth: logged once."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world/rover/left_cam", rr.Transform3D(translation=left_mount[:3, 3], mat3x3=left_mount[:3, :3]),
            static=True)
    rec.log("world/rover/left_cam", pinhole(rig.wac), static=True)
    if truth_landmarks is not None and len(truth_landmarks):
        shown = truth_landmarks[::max(1, len(truth_landmarks) // TERRAIN_POINTS_SHOWN)]
        rec.log("world/terrain", rr.Points3D(shown, radii=0.03, colors=(120, 100, 80)), static=True)
    if truth_positions is not None:
        rec.log("world/truth", rr.LineStrips3D([truth_positions], radii=rr.Radius.ui_points(3.0),
                                               colors=TRUTH_COLOUR), static=True)
        rec.log("map/truth", rr.GeoLineStrings(lat_lon=[lat_lon(origin, truth_positions)],
                                               radii=rr.Radius.ui_points(2.0), colors=TRUTH_COLOUR), static=True)
    # Styles are static so the per-stop logs carry geometry only (from_fields is cheaper).
    for config in configs:
        rgb = colour(config)
        for path in (estimate_path(config, "trajectory"), estimate_path(config, "trajectory/tail")):
            rec.log(path, rr.LineStrips3D.from_fields(radii=rr.Radius.ui_points(2.0), colors=rgb), static=True)
        rec.log(estimate_path(config, "covariance"), rr.Ellipsoids3D.from_fields(
            colors=rgb, fill_mode=rr.components.FillMode.MajorWireframe), static=True)
    for name, (_, per_config) in SERIES.items():
        for config in configs if per_config else [None]:
            rgb = colour(config) if config else (220, 220, 220)
            rec.log(series_path(name, config), rr.SeriesLines(colors=rgb, names=config or name), static=True)


MESH_POSTS = 200  # the orbital DTM's mesh, at most this many vertices a side (a software renderer draws it)
# The mesh is drawn this much low, plus twice the map's stated vertical error: the trajectories
# (the body's origin) stay above it, whatever the map's datum offset
MESH_DROP_M = 0.5
TEXTURE_PIXELS = 2048  # the orthoimage, at most this many pixels a side (a browser's texture limit)


@dataclass(frozen=True)
class OrbitalMapView:
    """An orbital map in rerun: its DTM as the 3-D view's ground, textured with its orthoimage,
    and the orthoimage as a 2-D map with the trajectories drawn on it (in its pixels). The map
    is shown where it says it is: its georeference error is what the orbital kind estimates."""

    orbital_map: OrbitalMap
    origin: LocalFrame

    @property
    def image(self):
        return self.orbital_map.orthoimage

    @property
    def shrink(self) -> int:
        """The orthoimage is logged every `shrink`-th pixel (a browser's texture limit)."""
        return max(1, int(np.ceil(max(self.image.values.shape) / TEXTURE_PIXELS)))

    def log_static(self, rec: rr.RecordingStream, truth_positions: np.ndarray | None) -> None:
        if self.image is None:
            return
        dtm, image = self.orbital_map.dtm, self.image
        step = max(1, int(np.ceil(max(dtm.values.shape) / MESH_POSTS)))
        rows, cols = slice(0, None, step), slice(0, None, step)
        vertices = post_enu(dtm, self.origin, rows, cols)
        height, width = dtm.values[rows, cols].shape
        vertices[~np.isfinite(vertices[:, 2]), 2] = np.nanmin(vertices[:, 2])
        vertices[:, 2] -= MESH_DROP_M + 2.0 * self.orbital_map.vertical_sigma_m
        x, y = dtm.centres()
        gx, gy = np.meshgrid(x[cols], y[rows])
        texcoords = np.column_stack([(gx.ravel() - image.x0_m) / (image.values.shape[1] * image.post_m),
                                     (image.y0_m - gy.ravel()) / (image.values.shape[0] * image.post_m)])
        index = np.arange(height * width).reshape(height, width)
        a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
        triangles = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
        shrink = self.shrink
        texture = np.repeat(image.values[::shrink, ::shrink, None], 3, axis=2)
        rec.log("world/orbital_map", rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles,
                                               vertex_texcoords=texcoords, albedo_texture=texture), static=True)
        rec.log("orbital_map/image", rr.Image(image.values[::shrink, ::shrink], draw_order=-1.0), static=True)
        if truth_positions is not None:
            rec.log("orbital_map/truth", rr.LineStrips2D([self.pixels(truth_positions)], colors=TRUTH_COLOUR,
                                                         radii=rr.Radius.ui_points(2.0)), static=True)

    def pixels(self, positions: np.ndarray) -> np.ndarray:
        """ENU positions (N, 3) as (column, row) of the image as logged."""
        xy = self.origin.to_map(positions)
        return np.column_stack([(xy[:, 0] - self.image.x0_m), (self.image.y0_m - xy[:, 1])]) / (
            self.image.post_m * self.shrink)

    def trajectory(self, config: str, positions: np.ndarray) -> tuple[str, rr.LineStrips2D]:
        return f"orbital_map/{config}", rr.LineStrips2D([self.pixels(positions)], colors=colour(config),
                                                        radii=rr.Radius.ui_points(2.0))


def pinhole(camera: Camera) -> rr.Pinhole:
    return rr.Pinhole(focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy],
                      resolution=[camera.width, camera.height], camera_xyz=rr.ViewCoordinates.RDF,
                      image_plane_distance=FRUSTUM_DEPTH_M)


def lat_lon(origin: LocalFrame, enu: np.ndarray) -> np.ndarray:
    return origin.to_geodetic(np.atleast_2d(enu))[:, :2]


def geo_line(origin: LocalFrame, positions: np.ndarray, config: str) -> rr.GeoLineStrings:
    return rr.GeoLineStrings(lat_lon=[lat_lon(origin, positions)], radii=rr.Radius.ui_points(2.0),
                             colors=colour(config))


def trajectory(positions: np.ndarray) -> rr.LineStrips3D:
    """Geometry only: the style was logged statically by `log_static`."""
    return rr.LineStrips3D.from_fields(strips=[np.asarray(positions, dtype=np.float32)])


def ellipsoids(centers: np.ndarray, covariances: np.ndarray) -> rr.Ellipsoids3D:
    """95 % position ellipsoids from world-frame 3x3 covariances (geometry only)."""
    half_sizes, quaternions = ellipsoid_axes(covariances)
    return rr.Ellipsoids3D.from_fields(centers=centers, half_sizes=half_sizes, quaternions=quaternions)


def ellipsoid_axes(covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(half sizes (N, 3), quaternions xyzw (N, 4)) of the 95 % ellipsoids of covariances (N, 3, 3)."""
    covariances = np.asarray(covariances).reshape(-1, 3, 3)
    values, vectors = np.linalg.eigh(0.5 * (covariances + np.swapaxes(covariances, 1, 2)))
    half = ELLIPSOID_SCALE_95 * np.sqrt(np.clip(values, 0.0, None))
    vectors[np.linalg.det(vectors) < 0, :, 2] *= -1.0  # a proper rotation
    return half, np.array([_xyzw(gtsam.Rot3(v).toQuaternion()) for v in vectors])


def _xyzw(q) -> list[float]:
    return [q.x(), q.y(), q.z(), q.w()]


def frustum_segments(world_T_cam: np.ndarray, camera: Camera, depth_m: float = FRUSTUM_DEPTH_M) -> np.ndarray:
    """Outline of a camera's field of view as 8 segments (8, 2, 3): centre to each image corner,
    then the image rectangle."""
    corners_px = np.array([[0.0, 0.0], [camera.width, 0.0], [camera.width, camera.height], [0.0, camera.height]])
    rays = np.column_stack([(corners_px[:, 0] - camera.cx) / camera.fx, (corners_px[:, 1] - camera.cy) / camera.fy,
                            np.ones(4)]) * depth_m
    corners = rays @ world_T_cam[:3, :3].T + world_T_cam[:3, 3]
    centre = np.broadcast_to(world_T_cam[:3, 3], (4, 3))
    edges = np.stack([centre, corners], axis=1)
    rectangle = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    return np.concatenate([edges, rectangle]).astype(np.float32)


def tie_strips(links: np.ndarray, landmark_ids: np.ndarray, landmarks: np.ndarray,
               site_positions: dict[int, np.ndarray]) -> np.ndarray:
    """A segment from each site to each landmark it tied, (N, 2, 3): one array, not a list of
    small ones, which rerun converts far slower."""
    index = {int(t): i for i, t in enumerate(landmark_ids)}
    pairs = [(index[track], stop) for track, stop in links.tolist() if track in index and stop in site_positions]
    if not pairs:
        return np.zeros((0, 2, 3), dtype=np.float32)
    rows, stops = zip(*pairs, strict=True)
    ends = np.asarray(landmarks)[list(rows)]
    starts = np.array([site_positions[s] for s in stops])
    return np.stack([starts, ends], axis=1).astype(np.float32)


@dataclass
class SeriesBuffer:
    """Scalars gathered stop by stop and sent as columns (one call per series) at checkpoints."""

    rows: dict[str, list[tuple[int, float, float, float]]] = field(default_factory=lambda: defaultdict(list))

    def add(self, path: str, stop: int, time_s: float, distance_m: float, value: float) -> None:
        self.rows[path].append((stop, time_s, distance_m, value))

    def send(self, rec: rr.RecordingStream) -> None:
        for path, rows in self.rows.items():
            if rows:
                stops, times, dist, values = zip(*rows, strict=True)
                rec.send_columns(path, indexes=time_columns(stops, times, dist),
                                 columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))
        self.rows.clear()
