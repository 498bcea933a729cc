"""Live rerun recording of a run: a `RunListener` that logs every stop as iSAM2 solves it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import rerun as rr

from ..evaluation.gps_check import gps_enu
from ..records import GroundTruth, Stop, Traverse
from ..solve.localizer import Localizer, StepResult
from . import rerun_scene as scene
from .rerun_sink import OpenRecording

# Every configuration is re-read, and what was logged sent, every this many stops (and at the
# end). A browser's viewer takes in a few chunks per frame, and a software-rendered one draws a
# few frames a second: sent more often, it falls behind the run.
REFRESH_EVERY_STOPS = 100
FEATURES = rr.AnnotationContext([(0, "new", (200, 200, 200)), (1, "tracked from the last stop", (60, 220, 60))])


@dataclass
class _PrimaryRows:
    """The primary configuration's per-stop logs, sent as columns at each checkpoint: a few
    calls per checkpoint instead of several per stop (the per-call cost dominates)."""

    when: list[tuple[int, float, float]] = field(default_factory=list)  # stop, time, distance
    tails: list[np.ndarray] = field(default_factory=list)  # the trajectory since the last refresh
    centres: list[np.ndarray] = field(default_factory=list)
    covariances: list[np.ndarray] = field(default_factory=list)
    rover: list[np.ndarray] = field(default_factory=list)
    features: list[np.ndarray] = field(default_factory=list)
    tracked: list[np.ndarray] = field(default_factory=list)

    def send(self, rec: rr.RecordingStream, tail_path: str, covariance_path: str) -> None:
        if not self.when:
            return
        stops, times, dist = zip(*self.when, strict=True)
        columns = scene.time_columns(stops, times, dist)
        rec.send_columns(tail_path, indexes=columns, columns=rr.LineStrips3D.columns(strips=self.tails))
        half, quaternions = scene.ellipsoid_axes(np.array(self.covariances))
        rec.send_columns(covariance_path, indexes=columns, columns=rr.Ellipsoids3D.columns(
            centers=np.array(self.centres), half_sizes=half, quaternions=quaternions))
        poses = np.array(self.rover)
        rec.send_columns("world/rover", indexes=columns,
                         columns=rr.Transform3D.columns(translation=poses[:, :3, 3], mat3x3=poses[:, :3, :3]))
        rec.send_columns("world/rover/left_cam/features", indexes=columns, columns=rr.Points2D.columns(
            positions=np.concatenate(self.features), class_ids=np.concatenate(self.tracked),
        ).partition([len(f) for f in self.features]))
        for rows in vars(self).values():
            rows.clear()


class RerunRecorder:
    """Logs a run into a rerun recording stop by stop, sent and flushed every `refresh_every`
    stops and at the end.

    Reading a configuration's whole estimate back from iSAM2 costs about a millisecond, so
    every configuration's trajectory (and the landmarks, when a site has passed) is re-read
    every `refresh_every` stops; in between only the primary configuration (the richest: it also
    drives the rover and camera) appends its newest pose and ellipsoid (`pancam-graph bench
    --rerun` measures what recording costs).
    """

    def __init__(self, recording: OpenRecording, refresh_every: int = REFRESH_EVERY_STOPS):
        self.recording = recording
        self.rec = recording.stream
        self.stopped = False  # the recording failed (a full disk, a stalled viewer): the run goes on
        self.refresh_every = refresh_every
        self.series = scene.SeriesBuffer()
        self.pending = _PrimaryRows()

    # -- RunListener ----------------------------------------------------------------------

    def start(self, traverse: Traverse, truth: GroundTruth | None, localizers: dict[str, Localizer]) -> None:
        self.traverse = traverse
        self.truth = truth
        self.localizers = localizers
        self.configs = list(localizers)
        self.primary = self.configs[-1]  # the richest configuration drives the rover and camera
        self.positions = {c: np.zeros((0, 3)) for c in self.configs}
        self.tail_start = dict.fromkeys(self.configs, 0)
        self.gps_outliers = dict.fromkeys(self.configs, 0)
        self.gps_times, self.gps_enu = gps_enu(traverse)  # fixes are inputs: converted once
        self.gps_lat_lon = np.array([[f.lat_deg, f.lon_deg] for f in traverse.gps_fixes]).reshape(-1, 2)
        # each fix is updated with the stop whose drive (or dwell) it falls in
        departures = np.array([s.departure_s for s in traverse.stops])
        self.gps_stops = np.minimum(np.searchsorted(departures, self.gps_times - 1e-3, side="left"),
                                    len(departures) - 1)
        self.last_stop = -1
        self.flagged: set[int] = set()  # stops whose fix the primary configuration flagged
        self.sites: dict[int, tuple[int, np.ndarray]] = {}  # stop -> (site id, position when logged)
        self.site_since_refresh = False
        self.distance_m = 0.0
        self.previous_tracks = np.zeros(0, dtype=np.int64)
        rig = traverse.rig
        maps = [m for m in traverse.measurements.get("orbital", ()) if m.orthoimage is not None]
        self.orbital = scene.OrbitalMapView(maps[0], traverse.origin) if maps else None
        self.rec.send_blueprint(scene.blueprint(self.configs, None if truth is None else truth.positions,
                                                orbital_map=self.orbital is not None))
        self.rec.log("world/rover/left_cam/features", rr.Points2D.from_fields(radii=2.0), FEATURES, static=True)
        scene.log_static(self.rec, self.configs, rig, traverse.body_T_nav().matrix(),
                         traverse.origin, None if truth is None else truth.positions,
                         None if truth is None else truth.landmarks)
        if self.orbital is not None:
            self.orbital.log_static(self.rec, None if truth is None else truth.positions)

    def step(self, stop: Stop, motion, steps: dict[str, StepResult]) -> None:
        if self.stopped:
            return
        k = self.last_stop = stop.index
        if motion is not None:
            self.distance_m += float(np.linalg.norm(motion.prev_T_curr.translation()))
        scene.set_stop_time(self.rec, k, stop.time_s, self.distance_m)
        when = (k, stop.time_s, self.distance_m)
        self.pending.when.append(when)
        refresh = (k + 1) % self.refresh_every == 0 or k + 1 == len(self.traverse.stops)
        self.site_since_refresh |= stop.is_site
        for config, localizer in self.localizers.items():
            current = self._log_estimate(config, localizer, k, refresh, self.site_since_refresh)
            step = steps[config]
            if self.truth is not None:
                self.series.add(scene.series_path("error_m", config), *when,
                                float(np.linalg.norm(current[:3, 3] - self.truth.positions[k])))
            self.series.add(scene.series_path("isam2_update_ms", config), *when, step.update_ms)
            self.series.add(scene.series_path("relinearized", config), *when, step.relinearized)
            if step.count("gps_fixes"):
                outliers = step.count("gps_outliers")
                self.gps_outliers[config] += outliers
                self.series.add(scene.series_path("gps_outliers", config), *when, self.gps_outliers[config])
                if outliers:
                    self.rec.log("events", rr.TextLog(
                        f"stop {k}: {config} flags {outliers} GPS fix(es) as outliers "
                        f"(Mahalanobis^2 {step.count('gps_mahalanobis2'):.1f})", level=rr.TextLogLevel.WARN))
                    if config == self.primary:
                        self.flagged.add(k)
            if config == self.primary:
                self.pending.rover.append(current)
                if stop.is_site:
                    self._log_site(stop, current)
        self._log_features(stop)
        if motion is not None:
            self.series.add(scene.series_path("vo_inliers"), *when, motion.vo_inliers)
            if motion.bridged:
                self.rec.log("events", rr.TextLog(
                    f"stop {k}: VO failed ({motion.vo_failure}); bridged by {motion.source}",
                    level=rr.TextLogLevel.WARN))
        if refresh:
            self.site_since_refresh = False
            self._send()

    def checkpoint(self, stop: Stop) -> None:
        """Nothing: the recording is sent at its own refreshes (a run that dies loses at most the
        stops since the last one from the recording, never from the results)."""

    def _send(self) -> None:
        """What was logged since the last send, the GPS fixes and the map; flushed."""
        self._send_pending()
        self._log_gps()
        for config in self.configs:
            self.rec.log(scene.map_path(config), scene.geo_line(self.traverse.origin, self.positions[config], config))
        self.rec.log("map/rover", rr.GeoPoints(lat_lon=scene.lat_lon(self.traverse.origin,
                                                                      self.positions[self.primary][-1]),
                                               radii=rr.Radius.ui_points(7.0), colors=scene.colour(self.primary)))
        self.stopped = not self.recording.flush()

    def finish(self, result) -> None:
        """The final estimates (after the closing relinearization or batch polish)."""
        if self.stopped:
            return
        self._send_pending()  # first: the final logs at the last stop must come after the live ones
        last = self.traverse.stops[-1]
        scene.set_stop_time(self.rec, last.index, last.time_s, self.distance_m)
        site_rows = [i for i, s in enumerate(self.traverse.stops) if s.is_site] + [len(self.traverse.stops) - 1]
        for config, c in result.configurations.items():
            self.positions[config] = c.world_T_body[:, :3, 3]
            self.rec.log(scene.estimate_path(config, "trajectory"), scene.trajectory(self.positions[config]))
            if self.orbital is not None:
                self.rec.log(*self.orbital.trajectory(config, self.positions[config]))
            self.rec.log(scene.estimate_path(config, "covariance"), scene.ellipsoids(
                self.positions[config][site_rows], c.position_covariance[site_rows]))
            if len(c.landmark_ids):
                self._log_landmarks(config, c.landmark_ids, c.landmark_positions, c.tie_links,
                                    {s.index: c.world_T_body[i, :3, 3] for i, s in enumerate(self.traverse.stops)})
        self.rec.log("events", rr.TextLog(f"finished: {len(self.traverse.stops)} stops, wall {result.wall_s:.1f} s"))
        self._send()

    # -- pieces ---------------------------------------------------------------------------

    def _send_pending(self) -> None:
        self.series.send(self.rec)
        self.pending.send(self.rec, scene.estimate_path(self.primary, "trajectory/tail"),
                          scene.estimate_path(self.primary, "covariance"))

    def _log_estimate(self, config: str, localizer: Localizer, k: int, refresh: bool, at_site: bool) -> np.ndarray:
        """Log the configuration's trajectory and current 95 % ellipsoid; return the current pose.
        Every configuration's whole trajectory is logged when refreshed (the primary's landmarks
        and tie links too after a site; the others' once, at the end). The primary's ellipsoid
        is logged at every stop, and so is its trajectory since the last refresh (its tail): the
        line follows the rover, without sending the whole line at every stop (more than a
        browser's viewer takes on a long traverse)."""
        if refresh:
            snapshot = localizer.snapshot()
            self.positions[config] = snapshot.world_T_body[:, :3, 3]
            self.tail_start[config] = len(self.positions[config]) - 1
            current = snapshot.world_T_body[-1]
            if at_site and config == self.primary and len(snapshot.landmark_ids):
                sites = {int(s): snapshot.world_T_body[i, :3, 3] for i, s in enumerate(snapshot.stops)}
                self._log_landmarks(config, snapshot.landmark_ids, snapshot.landmarks, localizer.tie_links(), sites)
        else:
            current = localizer.pose(k)
            if config != self.primary:
                return current
            self.positions[config] = np.vstack([self.positions[config], current[:3, 3]])
        covariance = localizer.position_covariance(k)
        if config == self.primary:
            self.pending.tails.append(self.positions[config][self.tail_start[config]:].astype(np.float32))
            self.pending.centres.append(current[:3, 3])
            self.pending.covariances.append(covariance)
            if refresh:
                self.rec.log(scene.estimate_path(config, "trajectory"), scene.trajectory(self.positions[config]))
        else:
            self.rec.log(scene.estimate_path(config, "trajectory"), scene.trajectory(self.positions[config]))
            self.rec.log(scene.estimate_path(config, "covariance"),
                         scene.ellipsoids(current[None, :3, 3], covariance[None]))
        if refresh and self.orbital is not None:
            self.rec.log(*self.orbital.trajectory(config, self.positions[config]))
        return current

    def _log_landmarks(self, config, ids, points, links, site_positions) -> None:
        rgb = scene.colour(config)
        self.rec.log(scene.estimate_path(config, "landmarks"), rr.Points3D(points, radii=0.12, colors=rgb))
        ties = scene.tie_strips(links, ids, points, site_positions)
        self.rec.log(scene.estimate_path(config, "ties"),
                     rr.LineStrips3D(ties, radii=rr.Radius.ui_points(0.5), colors=(*rgb, scene.TIE_ALPHA)))

    def _log_site(self, stop: Stop, world_T_body: np.ndarray) -> None:
        rig = self.traverse.rig
        # the latest site's frustums only: every site's, hundreds of lines, buried the trajectories
        segments = [scene.frustum_segments(world_T_body @ rig.body_T_left(f.pan_rad, f.tilt_rad).matrix(), rig.wac)
                    for f in stop.panorama]
        self.sites[stop.index] = (stop.site_id, world_T_body[:3, 3])
        if segments:
            self.rec.log("world/sites/panoramas", rr.LineStrips3D(np.concatenate(segments), radii=0.01,
                                                                  colors=(250, 210, 60)))
        self.rec.log("world/sites", rr.Points3D(np.array([p for _, p in self.sites.values()]), radii=0.3,
                                                colors=(250, 210, 60),
                                                labels=[f"site {i}" for i, _ in self.sites.values()]))
        self.rec.log("events", rr.TextLog(
            f"stop {stop.index}: site {stop.site_id}, panorama of {len(stop.panorama)} stereo frames"
            f" and {len(stop.hrc)} HRC frames"))

    def _log_features(self, stop: Stop) -> None:
        obs = stop.stereo
        self.pending.features.append(obs.uvv[:, [0, 2]])
        self.pending.tracked.append(np.isin(obs.track_ids, self.previous_tracks).astype(np.uint16))
        self.previous_tracks = obs.track_ids

    def _log_gps(self) -> None:
        """Every fix received so far; those the primary configuration flagged in red."""
        n = int(np.searchsorted(self.gps_stops, self.last_stop, side="right"))
        if n == 0:
            return
        flagged = np.isin(self.gps_stops[:n], list(self.flagged))
        colours = np.where(flagged[:, None], scene.OUTLIER_COLOUR, scene.GPS_COLOUR).astype(np.uint8)
        self.rec.log("world/gps", rr.Points3D(self.gps_enu[:n], radii=0.15, colors=colours))
        self.rec.log("map/gps", rr.GeoPoints(lat_lon=self.gps_lat_lon[:n], radii=rr.Radius.ui_points(3.0),
                                             colors=colours))

