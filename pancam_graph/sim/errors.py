"""What the simulated rover gets wrong and its estimator does not know ([errors], config.py's
SimulationErrors; magnitudes and sources in docs/simulation_errors.md):

- the stereo pair's calibration, drawn once a run: each camera's focal length and the
  baseline a little off the calibrated ones, the right camera turned a little;
- the mast's pan and tilt readings, per frame: the true angles rounded to the encoder's
  resolution;
- the navigation frames' features as the image front-end tracks them, not at white pixel noise:
  a feature's disparity error persists along its track, its pixel drifts from stop to stop;
- tie points between sites as the image matcher finds them, not by landmark identity: as
  many as it finds at that distance, each off by its matching error, a few of them near
  misses.

Each draws from a random stream of its own, and only when it is switched on: the ideal profile
simulates what the simulator always has, to the bit."""

from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from ..config import SimulationErrors
from ..geometry.calibration_error import NAMES as CALIBRATION_NAMES
from ..geometry.rig import Camera, Rig
from ..graph import tie_matching
from ..records import HrcFrame, PanoramaFrame, StereoObservations, Stop

CALIBRATION_STREAM, POINTING_STREAM, TIES_STREAM, TRACKING_STREAM = 31, 32, 33, 34
NOISE_STREAM = 35  # the measurement noise of a scenario's noise_seed (sim/__init__.py)

# The image front-end's navigation features against the renderer's depth (rendered short_trail
# seeds 0 and 5, denver_trail seed 1, realistic profile, 120 stops each, about 75,000 features
# followed from one stop to the next in each; scripts/vo_tracking_truth.py). Spreads are 1.4826
# MAD, the same in all three within 0.03 px.
# Of a stop's features 0.73-0.76 are tracked on to the next: 0.25 of those 3-6 m away, which
# leave the image as the rover drives on, and 0.81-0.90 of those beyond 10 m, which stay in it:
# a track still in view goes on with the latter
TRACK_SURVIVAL = 0.85
DISPARITY_SIGMA_PX = 0.58  # a feature's disparity error, 0.57-0.59 px
# ... which is 0.70-0.73 correlated from one stop to the next along a track, 0.54 two stops on,
# 0.42 at three, 0.29 at five, 0.17-0.19 at eight to twelve: a part the feature keeps (0.15 of
# the variance), a part that fades as the view changes (0.78, 0.7 of it kept a stop) and a part
# new at every stop; the three give 0.70 / 0.53 / 0.42 / 0.28 / 0.20, short_trail 0's within 0.01
DISPARITY_KEPT, DISPARITY_FADING, DISPARITY_FADE = 0.15, 0.78, 0.70
# The left pixel's error from where the feature was first found grows with the stops it is
# tracked: column 0.31-0.34 px after one stop, 0.50-0.54 after two, 0.88-0.92 after four,
# 1.69-1.71 after eight; row 0.11, 0.15, 0.22, 0.42-0.44 px. A drift of its own per track (the
# feature slides by the same amount each stop) and a move new at every stop fit both within
# 0.04 px: column 0.19 and 0.26 px a stop, row 0.036 and 0.106
DRIFT_SIGMA_PX = (0.19, 0.036)
MOVE_SIGMA_PX = (0.26, 0.106)


@dataclass(frozen=True)
class TrueRig:
    """The stereo pair as it really is, against the calibrated `rig` the estimator uses."""

    left: Camera
    right: Camera
    baseline_m: float
    left_R_right: np.ndarray  # the right camera's axes in the left camera's frame

    @classmethod
    def draw(cls, rig: Rig, errors: SimulationErrors, rng: np.random.Generator) -> TrueRig:
        def focal(camera: Camera, scale: float) -> Camera:
            return replace(camera, fx=camera.fx * scale, fy=camera.fy * scale)

        common = 1.0 + rng.normal(0.0, errors.focal_scale_sigma)
        left = focal(rig.wac, common)
        right = focal(rig.wac, common * (1.0 + rng.normal(0.0, errors.focal_difference_sigma)))
        baseline = rig.baseline_m * (1.0 + rng.normal(0.0, errors.baseline_scale_sigma))
        rotation = gtsam.Rot3.Expmap(rng.normal(0.0, np.deg2rad(errors.boresight_sigma_deg), 3)).matrix()
        return cls(left, right, baseline, rotation)

    @classmethod
    def of_state(cls, calibrated: Rig, state: dict[str, float]) -> TrueRig:
        """The pair a `state` (as `state` gives it) says the `calibrated` rig's really is."""
        common = 1.0 + state["focal_scale"]
        right_scale = common * (1.0 + state["right_focal_ratio"])
        camera = calibrated.wac
        rotation = gtsam.Rot3.Expmap(np.array([state[f"right_rotation_{axis}_rad"] for axis in "xyz"])).matrix()
        return cls(replace(camera, fx=camera.fx * common, fy=camera.fy * common),
                   replace(camera, fx=camera.fx * right_scale, fy=camera.fy * right_scale),
                   calibrated.baseline_m * (1.0 + state["baseline_scale"]), rotation)

    def state(self, calibrated: Rig) -> dict[str, float]:
        """The error as the stereo_calibration kind estimates it (geometry/calibration_error.py):
        the right camera's rotation vector (rad, left camera axes), its focal ratio to the left
        one's less 1, the left one's to the `calibrated` camera's less 1, and the baseline's ratio
        to the calibrated one less 1."""
        rotation = gtsam.Rot3.Logmap(gtsam.Rot3(self.left_R_right))
        return dict(zip(CALIBRATION_NAMES, (*map(float, rotation), self.right.fx / self.left.fx - 1.0,
                                            self.left.fx / calibrated.wac.fx - 1.0,
                                            self.baseline_m / calibrated.baseline_m - 1.0), strict=True))

    def left_point(self, u: np.ndarray, v: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """(n, 3) left-camera points at camera depth `depth_m` that the true left camera sees at
        pixels (u, v): what `observe` puts there, undone."""
        left = self.left
        return np.column_stack([(u - left.cx) / left.fx, (v - left.cy) / left.fy, np.ones(len(u))]) * depth_m[:, None]

    def observe(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) in the left image and u in the right one of left-camera points, through the
        true pair; in pixels of the calibrated (rectified) pair the estimator assumes."""
        uv = self.left.project(p_cam, distort=False)
        p_right = (p_cam - np.array([self.baseline_m, 0.0, 0.0])) @ self.left_R_right
        u_right = self.right.fx * p_right[:, 0] / p_right[:, 2] + self.right.cx
        return uv, u_right


def with_pointing_error(pan_rad: float, tilt_rad: float, errors: SimulationErrors,
                        rng: np.random.Generator) -> tuple[float, float]:
    """The true mast angles of a frame whose readings are (pan_rad, tilt_rad): anywhere within
    half the encoder's resolution of them."""
    half = 0.5 * np.deg2rad(errors.pan_tilt_resolution_deg)
    return pan_rad + rng.uniform(-half, half), tilt_rad + rng.uniform(-half, half)


def _site_ids(stop: Stop) -> np.ndarray:
    return np.unique(np.concatenate([f.observations.track_ids for f in stop.panorama]
                                    + [h.track_ids for h in stop.hrc] + [np.zeros(0, np.int64)]))


def match_ties(stops: list[Stop], positions: np.ndarray, n_landmarks: int, memory: int, hrc_scale: float,
               rng: np.random.Generator) -> tuple[list[Stop], list[int]]:
    """The stops with their sites' tie points as the image matcher finds them: a later site keeps
    the landmark ids of at most tie_matching.count(distance) of what it shares with each of the last
    `memory` sites (nearest first), each of them off by a matching error common to all its
    views at that site (HRC views `hrc_scale` times as many pixels); every other landmark an
    earlier site saw becomes a new one (a fresh id). Returns the stops and, per fresh id from
    n_landmarks on, the landmark it is (the truth's)."""
    fresh: list[int] = []
    carried: dict[int, set[int]] = {}  # the last `memory` site stops -> the ids their views carry
    seen_before: set[int] = set()  # every id an earlier site's views carry, kept as it grows: formed
    # again at each site, it grew as the square of the sites (9 s of mars_traverse's 10 km)
    out = list(stops)
    for k, stop in enumerate(stops):
        if stop.site_id is None or not (stop.panorama or stop.hrc):
            continue
        ids = _site_ids(stop)
        id_set = set(ids.tolist())
        matched: dict[int, np.ndarray] = {}
        for a in sorted(carried, reverse=True):  # the remembered sites, nearest first
            shared = sorted((id_set & carried[a]) - matched.keys())
            distance = float(np.linalg.norm(positions[k] - positions[a]))
            n = min(len(shared), int(rng.poisson(tie_matching.count(distance))))
            for landmark in rng.choice(np.array(shared, dtype=np.int64), n, replace=False) if n else ():
                matched[int(landmark)] = _tie_error(distance, rng)
        remap = {}
        for landmark in sorted((id_set & seen_before) - matched.keys()):  # not a copy of seen_before
            remap[landmark] = n_landmarks + len(fresh)
            fresh.append(landmark)
        out[k] = _with_ties(stop, remap, matched, hrc_scale)
        carried[k] = {remap.get(int(i), int(i)) for i in ids}
        seen_before |= carried[k]
        if len(carried) > memory:
            del carried[min(carried)]
    return out, fresh


def _tie_error(distance_m: float, rng: np.random.Generator) -> np.ndarray:
    """A tie's matching error (px) between sites this far apart: a near miss, or a 2-D Gaussian
    of the measured median."""
    if rng.random() < tie_matching.near_miss_share(distance_m):
        angle = rng.uniform(0.0, 2.0 * np.pi)
        return rng.uniform(*tie_matching.NEAR_MISS_PX) * np.array([np.cos(angle), np.sin(angle)])
    return rng.normal(0.0, tie_matching.sigma_px(distance_m), 2)


def _with_ties(stop: Stop, remap: dict[int, int], matched: dict[int, np.ndarray], hrc_scale: float) -> Stop:
    def ids_and_shift(track_ids: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        shift = np.array([matched.get(int(i), (0.0, 0.0)) for i in track_ids]).reshape(-1, 2) * scale
        return np.array([remap.get(int(i), int(i)) for i in track_ids], dtype=np.int64), shift

    panorama = []
    for frame in stop.panorama:
        ids, shift = ids_and_shift(frame.observations.track_ids, 1.0)
        uvv = frame.observations.uvv + np.column_stack([shift[:, 0], shift[:, 0], shift[:, 1]])
        panorama.append(PanoramaFrame(frame.pan_rad, frame.tilt_rad, StereoObservations(ids, uvv)))
    hrc = []
    for frame in stop.hrc:
        ids, shift = ids_and_shift(frame.track_ids, hrc_scale)
        hrc.append(HrcFrame(frame.pan_rad, frame.tilt_rad, ids, frame.uv + shift))
    return replace(stop, panorama=tuple(panorama), hrc=tuple(hrc))


class TrackingErrors:
    """The navigation frames' pixel errors as the image front-end makes them, in place of white
    noise: a feature is where it was first found; along its track its left pixel drifts (a
    slide of its own each stop and a new move) and its disparity is off by an error it partly
    keeps; a track ends after a few stops (TRACK_SURVIVAL) and the landmark, still seen, starts a
    new one under a new track id, as the front-end finds a feature again. Call once per
    navigation frame, in order, with the landmarks it sees."""

    ID_STRIDE = 2**32  # a landmark's n-th track is landmark id + n * ID_STRIDE

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.ids = np.zeros(0, dtype=np.int64)  # the last frame's landmarks, sorted, and their tracks:
        self.track = np.zeros(0, dtype=np.int64)  # how many tracks before this one
        self.state = np.zeros((0, 6))  # left error (u, v), drift (u, v), kept and fading disparity error

    def __call__(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame's track ids and the (len(ids), 3) errors of (u_left, u_right, v) px."""
        n = self.rng.normal(size=(len(ids), 7))
        survives = self.rng.random(len(ids)) < TRACK_SURVIVAL
        kept_sigma = DISPARITY_SIGMA_PX * np.sqrt(DISPARITY_KEPT)
        fading_sigma = DISPARITY_SIGMA_PX * np.sqrt(DISPARITY_FADING)
        new_sigma = DISPARITY_SIGMA_PX * np.sqrt(1.0 - DISPARITY_KEPT - DISPARITY_FADING)

        # each landmark's place among the last frame's: seen there, its track goes on or ends
        at = np.clip(np.searchsorted(self.ids, ids), 0, max(len(self.ids) - 1, 0))
        seen = (self.ids[at] == ids) if len(self.ids) else np.zeros(len(ids), dtype=bool)
        tracked = seen & survives
        track = np.where(seen, self.track[at] + ~survives, 0) if len(self.ids) else np.zeros(len(ids), dtype=np.int64)
        state = np.column_stack([np.zeros((len(ids), 2)), np.asarray(DRIFT_SIGMA_PX) * n[:, 0:2],
                                 kept_sigma * n[:, 2], fading_sigma * n[:, 3]])
        old = self.state[at[tracked]]
        state[tracked, 2:5] = old[:, 2:5]
        state[tracked, 0:2] = old[:, 0:2] + old[:, 2:4] + np.asarray(MOVE_SIGMA_PX) * n[tracked, 4:6]
        state[tracked, 5] = (DISPARITY_FADE * old[:, 5]
                             + np.sqrt(1.0 - DISPARITY_FADE**2) * fading_sigma * n[tracked, 3])
        order = np.argsort(ids)
        self.ids, self.track, self.state = ids[order], track[order], state[order]

        disparity = state[:, 4] + state[:, 5] + new_sigma * n[:, 6]
        errors = np.column_stack([state[:, 0], state[:, 0] - disparity, state[:, 1]])
        return ids + track * self.ID_STRIDE, errors
