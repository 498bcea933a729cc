"""One stop in: the motion from the previous stop and every kind's measurements become factors;
the stop's iSAM2 updates out (one, and one before each kind that reads the stop's marginals to
make its factors: Kind.update_before)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..errors import ConfigError
from ..frontend.motion import Motion
from ..graph import factors
from ..graph.frozen import pose_matrices
from ..graph.keys import L, T, X
from ..graph.smoother import RelinearizeThresholds, Smoother
from ..kinds import KINDS, STEP_COUNTERS, Kind, absolute, uses_vo
from ..kinds.base import NO_TIE_LINKS, MotionFactor, StepCounts
from ..records import GroundTruth, Stop, Traverse
from ..runtime.spill import Column


@dataclass(frozen=True)
class StepResult:
    """What one stop's iSAM2 update did."""

    stop: int
    update_ms: float  # iSAM2 update wall time of this stop
    relinearized: int  # variables iSAM2 relinearized in this stop's updates
    counts: dict[str, float | None]  # every kind's per-stop counter (kinds.STEP_COUNTERS), by name

    def count(self, name: str) -> float | None:
        return self.counts.get(name, STEP_COUNTERS.get(name))


@dataclass(frozen=True)
class InterpolatedPose:
    """A pose inserted at a measurement time between two stops."""

    key: int
    time_s: float
    prev_stop: int
    stop: int
    fraction: float  # of the motion from prev_stop to stop


@dataclass(frozen=True)
class Snapshot:
    """The current estimate of one configuration: every stop's pose so far and every landmark."""

    stops: np.ndarray  # (N,)
    world_T_body: np.ndarray  # (N, 4, 4)
    landmark_ids: np.ndarray  # (M,)
    landmarks: np.ndarray  # (M, 3) world


GPS_RELINEARIZE_SKIP = 10  # GTSAM's default; see EstimatorConfig.relinearize_skip


def smoother_for(estimator: EstimatorConfig, with_gps: bool = False) -> Smoother:
    """The smoother an estimator configuration asks for (`with_gps`: for a configuration with GPS)."""
    thresholds = RelinearizeThresholds(estimator.relinearize_rotation_rad, estimator.relinearize_translation_m,
                                       estimator.relinearize_scalar, estimator.relinearize_calibration)
    factorization = estimator.factorization.upper()
    if factorization == "AUTO":
        factorization = "CHOLESKY" if with_gps else "QR"
    check, skip = estimator.relinearize_check, estimator.relinearize_skip
    partial = check == "partial" or (check == "auto" and with_gps)
    if skip == "auto":
        skip = GPS_RELINEARIZE_SKIP if with_gps else 1
    return Smoother(thresholds, skip, estimator.window_m, estimator.wildfire_threshold, factorization, partial)


class Localizer:
    """Builds and solves the factor graph of one configuration (a list of kinds), one stop at a time."""

    def __init__(self, traverse: Traverse, kinds: list[str], estimator: EstimatorConfig, seed: int = 0):
        self.traverse = traverse
        self.kind_names = list(kinds)
        self.estimator = estimator
        self.smoother = smoother_for(estimator, with_gps=absolute(kinds))
        self.rng = np.random.default_rng(seed)
        self.stops = Column("q")  # every stop stepped, to files as the traverse goes on
        self.previous_stop: Stop | None = None
        self.bridged_stops = 0
        self.interpolated: list[InterpolatedPose] = []
        self._keys_at: dict[float, int] = {}  # this step's inserted poses by time
        self.kinds: dict[str, Kind] = {}
        for name in KINDS:  # registry order: a kind may hook into one built before it
            if name in self.kind_names:
                self.kinds[name] = KINDS[name](self)
        # How a raw odometry increment or a VO step becomes a factor when a kind models its error
        # (wheel slip, VO scale: Kind.builds_motion); None: the motion's own between factor.
        self.odometry_factor = self._motion_factor("odometry")
        self.vo_factor = self._motion_factor("vo")
        # How a site's stereo view becomes a factor when a kind models the pair's calibration
        # (Kind.builds_site_stereo); None: factors.stereo.
        stereo = self._only_builder([k for k in self.kinds.values() if k.builds_site_stereo], "the sites' stereo")
        self.site_stereo_factor = stereo.site_stereo_factor() if stereo else None
        self.site_stereo_pixels = stereo.site_stereo_pixels if stereo else None

    def _motion_factor(self, motion: str) -> MotionFactor | None:
        builder = self._only_builder([k for k in self.kinds.values() if k.builds_motion == motion],
                                     f"the {motion} steps'")
        return builder.motion_factor() if builder else None

    def _only_builder(self, builders: list[Kind], what: str) -> Kind | None:
        """The one kind that builds `what` factors in place of the plain ones, or None."""
        if len(builders) > 1:
            raise ConfigError(f"configuration {'+'.join(self.kind_names)}: kinds "
                              f"{' and '.join(k.name for k in builders)} both build {what} factors")
        return builders[0] if builders else None

    def kind(self, name: str) -> Kind:
        if name not in self.kinds:
            raise ConfigError(f"configuration {'+'.join(self.kind_names)} has no kind {name!r}")
        return self.kinds[name]

    @property
    def uses_vo(self) -> bool:
        return uses_vo(self.kind_names)

    # -- the step ---------------------------------------------------------------------------

    def step(self, stop: Stop, motion: Motion | None) -> StepResult:
        k = stop.index
        # what this stop's updates add (a site stop takes two, three with its ties weighed at the estimate)
        ms_before, relinearized_before = self.smoother.update_ms_sum, self.smoother.relinearized_sum
        if motion is None:
            self.smoother.add(factors.start_prior(self.traverse.start_world_T_body, self.traverse.start_sigmas))
            self.smoother.insert(X(k), gtsam.Pose3(self.traverse.start_world_T_body))
        else:
            self.smoother.clock_m += float(np.linalg.norm(motion.prev_T_curr.translation()))
            self._add_motion(self.previous_stop, stop, motion)
            self.bridged_stops += motion.bridged
        self.stops.append(k)

        counts = StepCounts()
        for kind in self.kinds.values():
            why = kind.update_before(stop)
            if why is not None:
                self.smoother.update(context=f"at stop {k}, {why}")
            kind.add(stop, counts)
        self.smoother.update(context=f"at stop {k}")
        for kind in self.kinds.values():
            why = kind.after_update(stop, counts)
            if why is not None:
                self.smoother.update(context=f"at stop {k}, {why}")
        self.previous_stop = stop
        self._keys_at.clear()
        ms = self.smoother.update_ms_sum - ms_before
        return StepResult(k, ms, self.smoother.relinearized_sum - relinearized_before, dict(counts))

    def _add_motion(self, prev: Stop, stop: Stop, motion: Motion) -> None:
        """The between factor(s) from the previous stop. Kinds that measure while the rover drives
        (GPS) get a pose at each of their times: the motion is split there by time. The split
        assumes constant velocity over the drive and an error that accumulates uniformly along it
        (a random walk), so each piece gets its share of the covariance; chained back together the
        pieces carry the information of the original factor (exactly for the translation, to first
        order for the rotation), so a configuration without such measurements is unchanged."""
        drive_s = stop.time_s - prev.departure_s
        times = sorted({t for kind in self.kinds.values() for t in kind.pose_times(prev, stop)})
        fractions = [(t - prev.departure_s) / drive_s for t in times]
        keys = [X(prev.index)]
        for t, a in zip(times, fractions, strict=True):
            key = T(len(self.interpolated))
            self.interpolated.append(InterpolatedPose(key, t, prev.index, stop.index, a))
            self._keys_at[t] = key
            keys.append(key)
        keys.append(X(stop.index))

        step, covariance, build = motion.prev_T_curr, motion.covariance, factors.between
        sensitivity = None  # a VO factor's (Kind.motion_factor): the step's calibration sensitivity
        if motion.odometry is not None and self.odometry_factor is not None:
            step, covariance = gtsam.Pose3(motion.odometry.prev_T_curr), motion.odometry.covariance
            build = self.odometry_factor
        elif motion.source == "vo" and self.vo_factor is not None:
            build, sensitivity = self.vo_factor, motion.calibration_sensitivity
        start = self.smoother.pose(keys[0])
        if len(keys) == 2:
            self._add_motion_factor(build, keys[0], keys[1], step, covariance, *self._vo_only(build, sensitivity, 1.0))
            self.smoother.insert(keys[1], start.compose(motion.prev_T_curr))
            return
        twist = gtsam.Pose3.Logmap(step)
        estimated_twist = gtsam.Pose3.Logmap(motion.prev_T_curr)
        bounds = [0.0, *fractions, 1.0]
        for key_a, key_b, a, b in zip(keys[:-1], keys[1:], bounds[:-1], bounds[1:], strict=True):
            piece = gtsam.Pose3.Expmap((b - a) * twist)
            self._add_motion_factor(build, key_a, key_b, piece, (b - a) * covariance,
                                    *self._vo_only(build, sensitivity, b - a))
            self.smoother.insert(key_b, start.compose(gtsam.Pose3.Expmap(b * estimated_twist)))

    def _vo_only(self, build: MotionFactor, sensitivity: np.ndarray | None, share: float) -> tuple:
        """The VO factor's last argument, the sensitivity of its share of the step; none for the others."""
        if build is not self.vo_factor:
            return ()
        return (None if sensitivity is None else share * sensitivity,)

    def _add_motion_factor(self, build: MotionFactor, *arguments) -> None:
        # a kind's motion factor may be a Python CustomFactor: its recipe goes with it (checkpoints)
        self.smoother.add(build(*arguments), rebuild=(build, arguments))

    def pose_key_at(self, time_s: float) -> int:
        """The pose inserted at `time_s` in this step (see Kind.pose_times)."""
        return self._keys_at[time_s]

    def finish(self) -> None:
        for kind in self.kinds.values():
            kind.finish()

    def close(self) -> None:
        """Let go of the kinds and the factor builders they lent (each refers back to this
        localizer): without those cycles the localizer and its graphs are freed the moment the
        run drops it, with no garbage collection (a full one walks every object of the process,
        0.1-0.25 s)."""
        self.kinds = {}
        self.odometry_factor = self.vo_factor = self.site_stereo_factor = self.site_stereo_pixels = None

    # -- queries (for listeners and results) -------------------------------------------------

    def pose(self, k: int) -> np.ndarray:
        """Current estimate of world_T_body at stop k (4x4)."""
        return self.smoother.pose(X(k)).matrix()

    def position_covariance(self, k: int) -> np.ndarray:
        """3x3 covariance (m^2) of the body position at stop k, in the smoother's window, in the
        world (ENU) frame."""
        cov = self.smoother.marginal_covariance(X(k))[3:, 3:]  # GTSAM: translation in the body frame
        rot = self.smoother.pose(X(k)).rotation().matrix()
        return rot @ cov @ rot.T

    def position_covariances(self) -> np.ndarray:
        """(N, 3, 3) position covariance of every stop so far, world frame: from the Bayes tree
        in the smoother's window; for a stop that left it, its marginal as it left, which goes
        with its estimate, frozen then (the whole graph would add what came after, which that
        estimate never saw)."""
        keys = [X(k) for k in self.stops]
        left, body = self.smoother.left_position_covariances(keys)
        gone = np.flatnonzero(left)
        # no values given: the poses as they left, which their covariances go with
        rotations = pose_matrices(self.smoother.stacked(gtsam.Values(), [keys[j] for j in gone], 12))[:, :3, :3]
        out = np.empty((len(keys), 3, 3))
        for j, rot in zip(gone, rotations, strict=True):
            out[j] = rot @ body[j] @ rot.T
        for j in np.flatnonzero(~left):
            out[j] = self.position_covariance(self.stops[j])
        return out

    @property
    def landmarks(self) -> set[int]:
        return set().union(*(kind.landmarks() for kind in self.kinds.values()))

    def tie_links(self) -> np.ndarray:
        """(K, 2) (track, site stop): every kind's ties."""
        return np.concatenate([NO_TIE_LINKS, *(kind.tie_links() for kind in self.kinds.values())])

    def true_values(self, truth: GroundTruth) -> gtsam.Values | None:
        """True values of the variables that are not stop poses or landmarks (for the CRLB): the
        poses inserted between stops, interpolated the same way; each kind's own (its
        `true_values`). None when one is unknown."""
        values = gtsam.Values()
        for p in self.interpolated:
            a, b = gtsam.Pose3(truth.world_T_body[p.prev_stop]), gtsam.Pose3(truth.world_T_body[p.stop])
            values.insert(p.key, a.slerp(p.fraction, b))
        for kind in self.kinds.values():
            if not kind.true_values(truth, values):
                return None
        return values

    def counters(self) -> dict:
        out: dict = {}
        for kind in self.kinds.values():
            out.update(kind.counters())
        return out

    def against_truth(self, truth: GroundTruth) -> dict:
        """The kinds' own variables against the truth (Kind.against_truth)."""
        out: dict = {}
        for kind in self.kinds.values():
            out.update(kind.against_truth(truth))
        return out

    def snapshot(self) -> Snapshot:
        """The current iSAM2 estimate."""
        return self._snapshot_of(self.smoother.window_estimate())

    def _snapshot_of(self, values: gtsam.Values) -> Snapshot:
        """Every stop's pose and every landmark: from `values` (the window's, or a whole
        estimate), the others as they left the window."""
        # the stops' poses, not those inserted between stops
        poses = pose_matrices(self.smoother.stacked(values, [X(k) for k in self.stops], 12))
        ids = np.array(sorted(self.landmarks), dtype=np.int64)
        # by key: GTSAM's extractPoint3 also reads every other vector as a point (the orbital
        # kind's 4-vectors, as three numbers of garbage)
        points = self.smoother.stacked(values, [L(t) for t in ids.tolist()], 3)
        return Snapshot(self.stops.to_numpy(), poses, ids, points)

    # -- results ---------------------------------------------------------------------------

    def final(self, batch: bool = False) -> Snapshot:
        """The estimate after closing relinearization passes (and, with `batch`, Levenberg-Marquardt
        over the whole graph): poses and landmarks from the same values."""
        self.smoother.settle()
        values = self.smoother.batch_polish(self.smoother.estimate()) if batch else self.smoother.window_estimate()
        return self._snapshot_of(values)
