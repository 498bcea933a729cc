"""Replay a finished results folder into rerun with the live run's entity paths and blueprint.

A results folder holds final estimates, so the replay shows the final (smoothed) trajectory
growing stop by stop, not how iSAM2's estimate evolved; that history is in the `.rrd` of
`run --rerun save`. Camera features are not in a results folder and are not replayed.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from ..store.results_folder import SavedRun
from . import rerun_scene as scene


def replay(run: SavedRun, rec: rr.RecordingStream) -> None:
    rig, origin = run.rig, run.origin
    configs = list(run.configurations)
    primary = configs[-1]
    rec.send_blueprint(scene.blueprint(configs, run.configurations[primary].world_T_body[:, :3, 3]))
    truth = run.truth_world_T_body
    scene.log_static(rec, configs, rig, run.body_T_nav, origin,
                     None if truth is None else truth[:, :3, 3], run.truth_landmarks)

    distance = np.cumsum(run.motion_translation_m)
    columns = scene.time_columns(run.stops, run.times_s, distance)
    n = len(run.stops)
    for name, c in run.configurations.items():
        positions = c.world_T_body[:, :3, 3]
        # The trajectory as it would stand at each stop: one growing strip per stop.
        rec.send_columns(scene.estimate_path(name, "trajectory"), indexes=columns,
                         columns=rr.LineStrips3D.columns(strips=[positions[: k + 1] for k in range(n)]))
        half, quaternions = scene.ellipsoid_axes(c.position_covariance)
        rec.send_columns(scene.estimate_path(name, "covariance"), indexes=columns,
                         columns=rr.Ellipsoids3D.columns(centers=positions, half_sizes=half,
                                                         quaternions=quaternions))
        if truth is not None:
            _series(rec, scene.series_path("error_m", name), columns,
                    np.linalg.norm(positions - truth[:, :3, 3], axis=1))
        _series(rec, scene.series_path("isam2_update_ms", name), columns, c.update_ms)
        _series(rec, scene.series_path("relinearized", name), columns, c.relinearized)
        fixes, outliers = _count(c, "gps_fixes"), _count(c, "gps_outliers")
        used = np.flatnonzero(fixes)
        if len(used):
            _series(rec, scene.series_path("gps_outliers", name),
                    scene.time_columns(run.stops[used], run.times_s[used], distance[used]),
                    np.cumsum(outliers[used]))
        if len(c.landmark_ids):
            rgb = scene.colour(name)
            rec.log(scene.estimate_path(name, "landmarks"), rr.Points3D(c.landmark_positions, radii=0.12, colors=rgb),
                    static=True)
            sites = {k: positions[k] for k in set(c.tie_links[:, 1].tolist())}
            rec.log(scene.estimate_path(name, "ties"), rr.LineStrips3D(
                scene.tie_strips(c.tie_links, c.landmark_ids, c.landmark_positions, sites),
                radii=rr.Radius.ui_points(0.5), colors=(*rgb, scene.TIE_ALPHA)), static=True)
        rec.log(scene.map_path(name), scene.geo_line(origin, positions, name), static=True)

    moved = run.vo_inliers >= 0
    _series(rec, scene.series_path("vo_inliers"),
            scene.time_columns(run.stops[moved], run.times_s[moved], distance[moved]), run.vo_inliers[moved])
    main = run.configurations[primary].world_T_body
    rec.send_columns("world/rover", indexes=columns,
                     columns=rr.Transform3D.columns(translation=main[:, :3, 3], mat3x3=main[:, :3, :3]))
    _log_sites(rec, run, rig, main, distance)
    if len(run.gps_times_s):
        # a fix is updated with the stop whose drive (or dwell) it falls in
        stop_of = np.minimum(np.searchsorted(run.departures_s, run.gps_times_s - 1e-3, side="left"), n - 1)
        flagged = (_count(run.configurations[primary], "gps_outliers")[stop_of] > 0) & run.gps_used
        colours = [scene.OUTLIER_COLOUR if f else scene.GPS_COLOUR if u else scene.HELD_OUT_COLOUR
                   for f, u in zip(flagged, run.gps_used, strict=True)]
        enu = origin.to_enu(run.gps_lat_lon_h[:, 0], run.gps_lat_lon_h[:, 1], run.gps_lat_lon_h[:, 2])
        rec.log("world/gps", rr.Points3D(enu, radii=0.15, colors=colours), static=True)
        rec.log("map/gps", rr.GeoPoints(lat_lon=run.gps_lat_lon_h[:, :2], radii=rr.Radius.ui_points(3.0),
                                        colors=colours), static=True)
    for stop, source, failure in run.bridged:
        scene.set_stop_time(rec, stop, run.times_s[stop], distance[stop])
        rec.log("events", rr.TextLog(f"stop {stop}: VO failed ({failure}); bridged by {source}",
                                     level=rr.TextLogLevel.WARN))


def _series(rec: rr.RecordingStream, path: str, columns, values) -> None:
    rec.send_columns(path, indexes=columns, columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))


def _log_sites(rec: rr.RecordingStream, run: SavedRun, rig, world_T_body: np.ndarray, distance: np.ndarray) -> None:
    """The site markers, and each site's frustums from its stop on (as live: the latest site's)."""
    strips: dict[int, list[np.ndarray]] = {}
    sites = {}
    for stop, site_id, camera, pan_deg, tilt_deg in run.panoramas:
        if camera != "wac":
            continue
        mount = rig.body_T_left(np.deg2rad(pan_deg), np.deg2rad(tilt_deg)).matrix()
        strips.setdefault(stop, []).append(scene.frustum_segments(world_T_body[stop] @ mount, rig.wac))
        sites[stop] = site_id
    if not sites:
        return
    for stop, segments in strips.items():
        scene.set_stop_time(rec, stop, run.times_s[stop], distance[stop])
        rec.log("world/sites/panoramas", rr.LineStrips3D(np.concatenate(segments), radii=0.01, colors=(250, 210, 60)))
    rec.log("world/sites", rr.Points3D(world_T_body[list(sites), :3, 3], radii=0.3, colors=(250, 210, 60),
                                       labels=[f"site {s}" for s in sites]), static=True)


def _count(configuration, name: str) -> np.ndarray:
    """A per-stop counter of steps.csv as integers (0 where the run has no such column)."""
    values = configuration.counts.get(name)
    if values is None:
        return np.zeros(len(configuration.world_T_body), dtype=int)
    return np.nan_to_num(values).astype(int)
