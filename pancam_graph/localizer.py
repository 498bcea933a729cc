"""One stop in: motion, site tie points, HRC and GPS become factors; one iSAM2 update out."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.stats import chi2

from .config import EstimatorConfig
from .frontend.motion import Motion
from .graph import factors, noise
from .graph.keys import L, X
from .graph.smoother import Smoother
from .records import Stop, Traverse
from .rig import triangulate_rectified

_SITE_MEMORY = 3  # earlier sites searched for tie points
# A GPS fix whose residual at the updated estimate fails this 3-dof chi-square test is
# flagged as an outlier (the robust kernel has already down-weighted it).
GPS_OUTLIER_GATE = float(chi2.ppf(0.99, 3))


@dataclass(frozen=True)
class LocalizerOptions:
    """Which measurements a configuration uses."""

    use_sites: bool = True
    use_hrc: bool = True
    use_gps: bool = True
    use_vo: bool = True  # False: dead reckoning alone gives the between factors


@dataclass
class _SiteObservations:
    """What one site saw: per track, its stereo and HRC measurements with their camera mounts."""

    stop: int
    stereo: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))
    hrc: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))


@dataclass(frozen=True)
class StepResult:
    """What one stop's iSAM2 update did."""

    stop: int
    update_ms: float
    relinearized: int  # variables iSAM2 relinearized in this update
    new_landmarks: int
    rejected_ties: int
    gps_mahalanobis2: float | None  # squared Mahalanobis distance of this stop's fix after the update
    gps_outlier: bool

    @property
    def gps_used(self) -> bool:
        return self.gps_mahalanobis2 is not None


@dataclass(frozen=True)
class Snapshot:
    """The current estimate of one configuration: every pose so far and every landmark."""

    stops: np.ndarray  # (N,)
    world_T_body: np.ndarray  # (N, 4, 4)
    landmark_ids: np.ndarray  # (M,)
    landmarks: np.ndarray  # (M, 3) world


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
        self.landmark_sites: dict[int, list[int]] = defaultdict(list)  # track -> site stops seeing it
        self.stops: list[int] = []
        self.bridged_stops = 0
        self.rejected_ties = 0
        self.rejected_hrc = 0

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
        gps_enu = None
        if stop.gps is not None and self.options.use_gps:
            gps_enu = self._add_gps(stop)
        ms = self.smoother.update(context=f"at stop {k}")
        d2 = self._gps_mahalanobis2(stop, gps_enu) if gps_enu is not None else None
        outlier = d2 is not None and d2 > GPS_OUTLIER_GATE
        return StepResult(k, ms, self.smoother.relinearized[-1], new_landmarks, rejected, d2, outlier)

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
        stereo = site.stereo.get(track, ())
        for mount, uvv in stereo:
            self.smoother.add(factors.stereo(site.stop, track, uvv, self.stereo_calibration, mount, self.tie_noise))
        if stereo:
            self.landmark_sites[track].append(site.stop)
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

    def _add_gps(self, stop: Stop) -> np.ndarray:
        fix = stop.gps
        enu = self.traverse.origin.to_enu(fix.lat_deg, fix.lon_deg, fix.h_m)[0]
        model = noise.robust(self.gps_kernel, noise.gps_position(fix.sigma_horizontal_m, fix.sigma_vertical_m))
        self.smoother.add(factors.gps(stop.index, enu, self.traverse.gps_lever_arm_m, model))
        return enu

    def _gps_mahalanobis2(self, stop: Stop, enu: np.ndarray) -> float:
        antenna = self.smoother.pose(X(stop.index)).transformFrom(self.traverse.gps_lever_arm_m)
        sigmas = np.array([stop.gps.sigma_horizontal_m, stop.gps.sigma_horizontal_m, stop.gps.sigma_vertical_m])
        return float(np.sum(((antenna - enu) / sigmas) ** 2))

    # -- queries (for listeners and results) -------------------------------------------------

    def pose(self, k: int) -> np.ndarray:
        """Current estimate of world_T_body at stop k (4x4)."""
        return self.smoother.pose(X(k)).matrix()

    def position_covariance(self, k: int) -> np.ndarray:
        """3x3 covariance (m^2) of the body position at stop k in the world (ENU) frame."""
        cov = self.smoother.marginal_covariance(X(k))[3:, 3:]  # GTSAM: translation in the body frame
        rot = self.smoother.pose(X(k)).rotation().matrix()
        return rot @ cov @ rot.T

    def snapshot(self) -> Snapshot:
        """The current iSAM2 estimate."""
        return self._snapshot_of(self.smoother.estimate())

    def _snapshot_of(self, values: gtsam.Values) -> Snapshot:
        flat = gtsam.utilities.extractPose3(values)  # rows: R row-major (9), t (3); in key order
        poses = np.zeros((len(flat), 4, 4))
        poses[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
        poses[:, :3, 3] = flat[:, 9:]
        poses[:, 3, 3] = 1.0
        ids = np.array(sorted(self.landmarks), dtype=np.int64)
        points = gtsam.utilities.extractPoint3(values) if len(ids) else np.zeros((0, 3))
        return Snapshot(np.asarray(self.stops), poses, ids, points)

    def tie_links(self) -> list[tuple[int, int]]:
        """(track, site stop) for every landmark and every site whose panorama observed it."""
        return [(track, stop) for track in sorted(self.landmark_sites) for stop in self.landmark_sites[track]]

    # -- results ---------------------------------------------------------------------------

    def final(self, batch: bool = False) -> Snapshot:
        """The estimate after closing relinearization passes (and, with `batch`, Levenberg-Marquardt
        over the whole graph): poses and landmarks from the same values."""
        self.smoother.settle()
        values = self.smoother.estimate()
        if batch:
            values = self.smoother.batch_polish(values)
        return self._snapshot_of(values)
