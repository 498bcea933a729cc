"""One stop in: motion, site tie points, HRC and GPS become factors; one iSAM2 update out."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.stats import chi2

from .config import EstimatorConfig
from .frontend.motion import Motion
from .graph import factors, noise, tie_gate
from .graph.keys import L, X
from .graph.smoother import Smoother
from .graph.tie_gate import RelativePose, SitePoint
from .records import Stop, Traverse

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
    points: dict[int, SitePoint | None] = field(default_factory=dict)  # per track, its body frame


@dataclass(frozen=True)
class _LandmarkReference:
    """The site that first triangulated a landmark and that triangulation (its body frame): what
    later views of the landmark must agree with."""

    stop: int
    point: SitePoint


@dataclass(frozen=True)
class StepResult:
    """What one stop's iSAM2 update did."""

    stop: int
    update_ms: float  # iSAM2 update wall time of this stop
    relinearized: int  # variables iSAM2 relinearized in this stop's updates
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
        self.references: dict[int, _LandmarkReference] = {}
        self._relative_cache: dict[tuple[int, int], RelativePose] = {}  # these two: one site's step
        self._site_poses: dict[int, gtsam.Pose3] = {}
        self.rejected_ties = 0  # candidate tie points whose two sites disagree
        self.rejected_tie_views = 0  # later sites' views of a landmark that disagree with it
        self.rejected_hrc = 0

    # -- the step ---------------------------------------------------------------------------

    def step(self, stop: Stop, motion: Motion | None) -> StepResult:
        k = stop.index
        updates = len(self.smoother.update_ms)  # a site stop takes two iSAM2 updates
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
        self.smoother.update(context=f"at stop {k}")
        d2 = self._gps_mahalanobis2(stop, gps_enu) if gps_enu is not None else None
        outlier = d2 is not None and d2 > GPS_OUTLIER_GATE
        ms, relinearized = sum(self.smoother.update_ms[updates:]), sum(self.smoother.relinearized[updates:])
        return StepResult(k, ms, relinearized, new_landmarks, rejected, d2, outlier)

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
        obs.points = tie_gate.site_points(obs.stereo, self.rig, self.traverse.image_noise_px)
        return obs

    def _site_pose(self, stop: int) -> gtsam.Pose3:
        """A site's current pose estimate (cached for this site's step)."""
        if stop not in self._site_poses:
            self._site_poses[stop] = self.smoother.pose(X(stop))
        return self._site_poses[stop]

    def _relative(self, a: int, b: int) -> RelativePose:
        """Site pose b seen from site pose a, with its covariance (cached for this site's step)."""
        if (a, b) not in self._relative_cache:
            joint = self.smoother.joint_marginal_covariance(X(a), X(b))
            self._relative_cache[(a, b)] = RelativePose.from_joint(self._site_pose(a), self._site_pose(b), joint)
        return self._relative_cache[(a, b)]

    def _agrees(self, reference: _LandmarkReference, stop: int, seen: SitePoint) -> bool:
        d2 = tie_gate.disagreement2(reference.point, seen, self._relative(reference.stop, stop))
        return d2 <= tie_gate.AGREEMENT_GATE

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

        # The gate needs this site's pose in the Bayes tree (its relative covariance to the
        # earlier sites); the motion factor alone puts it there.
        self.smoother.update(context=f"at stop {stop.index}, before its tie points")
        self._relative_cache.clear()
        self._site_poses.clear()
        added = rejected = 0
        for track in tracks:
            earlier = candidates[track]
            then, now = earlier.points[track], current.points[track]
            if then is None or now is None:
                rejected += 1
                continue
            reference = _LandmarkReference(earlier.stop, then)
            if not self._agrees(reference, current.stop, now):
                rejected += 1
                continue
            self.smoother.insert(L(track), self._site_pose(earlier.stop).transformFrom(then.p_body))
            self.smoother.add(factors.landmark_anchor(earlier.stop, track, then.p_body))
            self.landmarks.add(track)
            self.references[track] = reference
            for site in recent:
                self._add_observations(site, track, gated=site is not earlier)
            self._add_observations(current, track, gated=False)
            added += 1
        # Landmarks already in the graph (tied earlier) seen again from here.
        for track in sorted(current.stereo.keys() & (self.landmarks - set(tracks))):
            self._add_observations(current, track, gated=True)

        self.rejected_ties += rejected
        self.sites.append(current)
        return added, rejected

    def _add_observations(self, site: _SiteObservations, track: int, gated: bool) -> None:
        """The site's stereo and HRC measurements of a landmark. `gated`: the stereo ones only if
        they agree with the landmark's reference triangulation."""
        stereo = site.stereo.get(track, ())
        if stereo and gated:
            seen = site.points[track]
            if seen is None or not self._agrees(self.references[track], site.stop, seen):
                self.rejected_tie_views += 1
                stereo = ()
        for mount, uvv in stereo:
            self.smoother.add(factors.stereo(site.stop, track, uvv, self.stereo_calibration, mount, self.tie_noise))
        if stereo:
            self.landmark_sites[track].append(site.stop)
        hrc = site.hrc.get(track, ())
        if not hrc:
            return
        p_world = self.smoother.point(L(track))
        world_T_body = self._site_pose(site.stop)
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
