"""One stop in: motion, site tie points, HRC and GPS become factors; one iSAM2 update out."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import gtsam
import numpy as np

from .config import EstimatorConfig
from .frontend.motion import Motion
from .graph import factors, noise
from .graph.keys import L, X
from .graph.smoother import Smoother, poses_array
from .records import Stop, Traverse
from .rig import triangulate_rectified

_SITE_MEMORY = 3  # earlier sites searched for tie points


@dataclass(frozen=True)
class LocalizerOptions:
    """Which measurements a configuration uses."""

    use_sites: bool = True
    use_hrc: bool = True
    use_gps: bool = True


@dataclass
class _SiteObservations:
    """What one site saw: per track, its stereo and HRC measurements with their camera mounts."""

    stop: int
    stereo: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))
    hrc: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))


@dataclass(frozen=True)
class StepResult:
    stop: int
    update_ms: float
    new_landmarks: int
    rejected_ties: int
    gps_used: bool


class Localizer:
    """Builds and solves the factor graph of one configuration, one stop at a time."""

    def __init__(self, traverse: Traverse, options: LocalizerOptions, estimator: EstimatorConfig, seed: int = 0):
        self.traverse = traverse
        self.options = options
        self.rig = traverse.rig
        self.smoother = Smoother()
        self.stereo_calibration = self.rig.stereo_calibration()
        self.hrc_calibration = self.rig.hrc.gtsam_calibration() if self.rig.hrc else None
        self.tie_noise = noise.robust(estimator.tie_kernel, noise.stereo_pixels(traverse.image_noise_px))
        # HRC residuals start large (landmarks come from the WAC), so only a convex kernel keeps
        # them pulling: Huber, whatever the tie-point kernel is.
        self.hrc_noise = noise.robust("huber", noise.image_pixels(traverse.image_noise_px))
        self.hrc_gate_px = estimator.hrc_gate_px
        self.gps_kernel = estimator.gps_kernel
        self.tie_points_per_site = estimator.tie_points_per_site
        self.rng = np.random.default_rng(seed)
        self.sites: list[_SiteObservations] = []
        self.landmarks: set[int] = set()
        self.stops: list[int] = []
        self.bridged_stops = 0
        self.rejected_ties = 0
        self.rejected_hrc = 0
        self.gps_fixes_used = 0

    # -- the step ---------------------------------------------------------------------------

    def step(self, stop: Stop, motion: Motion | None) -> StepResult:
        k = stop.index
        if motion is None:
            self.smoother.add(factors.start_prior(self.traverse.start_world_T_body, self.traverse.start_sigmas))
            self.smoother.insert(X(k), gtsam.Pose3(self.traverse.start_world_T_body))
        else:
            prev = self.stops[-1]
            self.smoother.add(factors.motion(prev, k, motion.prev_T_curr, motion.covariance))
            self.smoother.insert(X(k), self.smoother.pose(X(prev)).compose(motion.prev_T_curr))
            self.bridged_stops += motion.bridged
        self.stops.append(k)

        new_landmarks = rejected = 0
        if stop.is_site and self.options.use_sites:
            new_landmarks, rejected = self._add_site(stop)
        gps_used = False
        if stop.gps is not None and self.options.use_gps:
            self._add_gps(stop)
            gps_used = True
        ms = self.smoother.update(context=f"at stop {k}")
        return StepResult(k, ms, new_landmarks, rejected, gps_used)

    # -- sites: tie points between panoramas ------------------------------------------------

    def _collect(self, stop: Stop) -> _SiteObservations:
        obs = _SiteObservations(stop.index)
        for frame in stop.panorama:
            mount = self.rig.body_T_left(frame.pan_rad, frame.tilt_rad)
            for track, uvv in zip(frame.observations.track_ids, frame.observations.uvv, strict=True):
                obs.stereo[int(track)].append((mount, uvv))
        if self.options.use_hrc and self.hrc_calibration is not None:
            for frame in stop.hrc:
                mount = self.rig.body_T_hrc(frame.pan_rad, frame.tilt_rad)
                for track, uv in zip(frame.track_ids, frame.uv, strict=True):
                    obs.hrc[int(track)].append((mount, uv))
        return obs

    def _world_point(self, site: _SiteObservations, track: int) -> np.ndarray | None:
        """Mean of the site's triangulations of the track, in the world, at the current estimate."""
        world_T_body = self.smoother.pose(X(site.stop))
        points = []
        for mount, uvv in site.stereo[track]:
            p = triangulate_rectified([uvv[0]], [uvv[1]], [uvv[2]], self.rig.wac, self.rig.baseline_m)[0]
            if np.all(np.isfinite(p)) and p[2] > 0.5:
                points.append(world_T_body.compose(mount).transformFrom(p))
        return np.mean(points, axis=0) if points else None

    def _add_site(self, stop: Stop) -> tuple[int, int]:
        current = self._collect(stop)
        recent = self.sites[-_SITE_MEMORY:]
        candidates: dict[int, _SiteObservations] = {}
        for earlier in recent:
            for track in earlier.stereo.keys() & current.stereo.keys():
                if track not in self.landmarks:
                    candidates.setdefault(track, earlier)
        tracks = sorted(candidates)
        if len(tracks) > self.tie_points_per_site:
            tracks = sorted(self.rng.choice(tracks, self.tie_points_per_site, replace=False).tolist())

        added = rejected = 0
        for track in tracks:
            earlier = candidates[track]
            p_then, p_now = self._world_point(earlier, track), self._world_point(current, track)
            if p_then is None or p_now is None:
                rejected += 1
                continue
            rng_m = np.linalg.norm(p_then - self.smoother.pose(X(earlier.stop)).translation())
            # Gate against false matches; generous enough for VO drift between sites.
            if np.linalg.norm(p_then - p_now) > 2.0 + 0.1 * rng_m:
                rejected += 1
                continue
            self.smoother.insert(L(track), p_then)
            self.smoother.add(factors.landmark_anchor(track, p_then))
            self.landmarks.add(track)
            for site in recent:
                self._add_observations(site, track)
            added += 1
        # Landmarks already in the graph (tied earlier) seen again from here.
        for track in current.stereo.keys() & self.landmarks:
            self._add_observations(current, track)

        self.rejected_ties += rejected
        self.sites.append(current)
        return added, rejected

    def _add_observations(self, site: _SiteObservations, track: int) -> None:
        for mount, uvv in site.stereo.get(track, ()):
            self.smoother.add(factors.stereo(site.stop, track, uvv, self.stereo_calibration, mount, self.tie_noise))
        hrc = site.hrc.get(track, ())
        if not hrc:
            return
        p_world = self.smoother.point(L(track))
        world_T_body = self.smoother.pose(X(site.stop))
        for mount, uv in hrc:
            # An HRC false match pulls harder than the WAC can resist (7x the angular
            # resolution), so HRC measurements must agree with the WAC landmark first.
            camera = gtsam.PinholeCameraCal3_S2(world_T_body.compose(mount), self.hrc_calibration)
            p_cam = camera.pose().transformTo(p_world)
            if p_cam[2] <= 0 or np.linalg.norm(camera.project(p_world) - uv) > self.hrc_gate_px:
                self.rejected_hrc += 1
                continue
            self.smoother.add(factors.projection(site.stop, track, uv, self.hrc_calibration, mount, self.hrc_noise))

    # -- GPS -------------------------------------------------------------------------------

    def _add_gps(self, stop: Stop) -> None:
        fix = stop.gps
        enu = self.traverse.origin.to_enu(fix.lat_deg, fix.lon_deg, fix.h_m)[0]
        model = noise.robust(self.gps_kernel, noise.gps_position(fix.sigma_horizontal_m, fix.sigma_vertical_m))
        self.smoother.add(factors.gps(stop.index, enu, self.traverse.gps_lever_arm_m, model))
        self.gps_fixes_used += 1

    # -- results ---------------------------------------------------------------------------

    def trajectory(self, batch: bool = False) -> np.ndarray:
        """Estimated world_T_body (N, 4, 4) of every stop so far."""
        self.smoother.settle()
        values = self.smoother.estimate()
        if batch:
            values = self.smoother.batch_polish(values)
        return poses_array(values, [X(k) for k in self.stops])
