"""Scenario -> simulated traverse (what the rover records) and ground truth (kept apart)."""

from __future__ import annotations

import dataclasses
import zlib

import gtsam
import numpy as np

from ..config import Scenario
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import rig_preset
from ..kinds import KINDS
from ..records import GroundTruth, PanoramaFrame, SlipPrior, Stop, Traverse
from .errors import (
    CALIBRATION_STREAM,
    NOISE_STREAM,
    POINTING_STREAM,
    TIES_STREAM,
    TRACKING_STREAM,
    TrackingErrors,
    TrueRig,
    match_ties,
    with_pointing_error,
)
from .sensors import LandmarkField, dead_reckoning, gps_fix, observe_hrc, observe_stereo
from .world import dense_path, landmark_field, rover_poses, site_stops, stop_distances


def _in_ranges(s: float, ranges: list[tuple[float, float]]) -> bool:
    return any(a <= s <= b for a, b in ranges)


def simulate(scenario: Scenario, seed: int | None = None) -> tuple[Traverse, GroundTruth]:
    """Simulate the scenario. The same (scenario, seed) always gives the same traverse."""
    seed = scenario.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    rig = rig_preset(scenario.rig)
    frame = LocalFrame(scenario.origin.lat_deg, scenario.origin.lon_deg, scenario.origin.h_m, scenario.origin.body)
    cam_cfg = scenario.camera

    path = dense_path(scenario.path)
    stop_s = stop_distances(path, scenario.path, rng)
    poses = rover_poses(path, stop_s)
    landmarks, terrain = landmark_field(path, scenario.terrain, rng, np.random.default_rng([seed, 3]))
    field = LandmarkField(landmarks)
    sites = set(site_stops(stop_s, scenario.sites, rng)) if scenario.sites.enabled else set()
    # From here on the stream draws measurement noise; another noise seed draws it anew over the
    # same world (the calibration's and the pointing's streams stay the seed's)
    redraw: list[int] = [] if scenario.noise_seed is None else [scenario.noise_seed]
    if redraw:
        rng = np.random.default_rng([seed, NOISE_STREAM, *redraw])

    tilt = np.deg2rad(cam_cfg.traverse_tilt_deg)
    body_T_nav = rig.body_T_left(0.0, tilt)
    pans = np.deg2rad(np.arange(*scenario.sites.pan_range_deg, scenario.sites.pan_step_deg))
    hrc_pans = np.deg2rad(np.arange(*scenario.sites.pan_range_deg,
                                    scenario.sites.hrc_pan_step_deg or scenario.sites.pan_step_deg))
    site_range = (1.0, scenario.sites.max_range_m)

    # The traverse's wheel slip: one draw per traverse (terrain, load), from its own stream so
    # that the rest of the simulation does not depend on it.
    dr_cfg = scenario.dead_reckoning
    traverse_slip = np.random.default_rng([seed, 1]).normal(dr_cfg.wheel_slip_mean, dr_cfg.wheel_slip_bias_sigma)
    at_stops = scenario.gps.enabled and scenario.gps.rate_hz is None

    errors = scenario.errors
    true_rig = (TrueRig.draw(rig, errors, np.random.default_rng([seed, CALIBRATION_STREAM]))
                if errors.calibration else None)
    pointing_rng = np.random.default_rng([seed, POINTING_STREAM]) if errors.pan_tilt_resolution_deg else None
    tracking = (TrackingErrors(np.random.default_rng([seed, TRACKING_STREAM, *redraw]))
                if errors.stereo_tracking == "measured" else None)

    mast_angles: dict[int, list[tuple[float, float]]] = {}  # GroundTruth.mast_angles

    def pointed(stop: int, pan: float, tilt: float) -> tuple[float, float] | None:
        """The mast's true angles for readings (pan, tilt) at a stop, kept for the truth; None
        where they are the readings."""
        if pointing_rng is None:
            return None
        angles = with_pointing_error(pan, tilt, errors, pointing_rng)
        mast_angles.setdefault(stop, []).append(angles)
        return angles

    def true_left(stop: int, pan: float, tilt: float) -> gtsam.Pose3 | None:
        angles = pointed(stop, pan, tilt)
        return None if angles is None else rig.body_T_left(*angles)

    stops, fixes, time_s, site_id = [], [], 0.0, 0
    for k, s in enumerate(stop_s):
        dr = None
        if k > 0:
            dt = (s - stop_s[k - 1]) / scenario.path.speed_mps + scenario.path.dwell_s
            time_s += dt
            if dr_cfg.enabled:
                dr = dead_reckoning(poses[k - 1], poses[k], dt, dr_cfg, traverse_slip, rng)
        stereo = observe_stereo(field, poses[k], body_T_nav, rig, cam_cfg.vo_range_m, cam_cfg, rng, true_rig,
                                tracking=tracking)
        panorama, hrc, this_site = (), (), None
        if k in sites:
            this_site, site_id = site_id, site_id + 1
            panorama = tuple(
                PanoramaFrame(
                    float(p), float(np.deg2rad(t)),
                    observe_stereo(
                        field, poses[k], rig.body_T_left(p, np.deg2rad(t)), rig, site_range, cam_cfg, rng, true_rig,
                        true_left(k, p, np.deg2rad(t)),
                    ),
                )
                for p in pans
                for t in scenario.sites.tilts_deg
            )
            if scenario.sites.hrc and rig.hrc is not None:
                hrc_tilt = np.deg2rad(scenario.sites.hrc_tilt_deg)
                hrc = tuple(
                    observe_hrc(field, poses[k], float(p), hrc_tilt, rig, site_range, cam_cfg, rng,
                                pointed(k, float(p), hrc_tilt))
                    for p in hrc_pans
                )
        if at_stops and k % scenario.gps.every_n_stops == 0 and not _in_ranges(s, scenario.gps.dropouts):
            fixes.append(gps_fix(poses[k], time_s, scenario.gps, frame, rng))
        dwell = scenario.path.dwell_s + (scenario.sites.dwell_s if k in sites else 0.0)
        stops.append(Stop(k, time_s, stereo, this_site, panorama, hrc, dr, dwell_s=dwell))
        if k in sites:
            time_s += scenario.sites.dwell_s
    landmarks = field.points
    if errors.tie_matching == "measured":
        stops, fresh = match_ties(stops, poses[:, :3, 3], len(landmarks), scenario.estimator.sites.memory,
                                  rig.hrc.fx / rig.wac.fx if rig.hrc is not None else 1.0,
                                  np.random.default_rng([seed, TIES_STREAM, *redraw]))
        landmarks = np.vstack([landmarks, landmarks[fresh]]) if fresh else landmarks
    if scenario.gps.enabled and scenario.gps.rate_hz is not None:
        fixes = _fixes_while_driving(scenario, path, stops, stop_s, frame, np.random.default_rng([seed, 2]))

    est = scenario.estimator
    start_sigmas = np.array([np.deg2rad(est.start_sigma_deg)] * 3 + [est.start_sigma_m] * 3)
    # The surveyed start pose is off the truth by what the start prior says it may be; an exact
    # one would make every estimate look better than its covariance (and than the bound).
    # Drawn last, so the rest of the simulation is the same as without it.
    survey_error = gtsam.Pose3.Expmap(rng.normal(0.0, start_sigmas))
    surveyed_start = (gtsam.Pose3(poses[0]) * survey_error).matrix()
    traverse = Traverse(
        name=scenario.name,
        rig=rig,
        origin=frame,
        stops=tuple(stops),
        traverse_tilt_rad=float(tilt),
        image_noise_px=cam_cfg.image_noise_px,
        gps_lever_arm_m=np.asarray(scenario.gps.lever_arm_m, dtype=float),
        start_world_T_body=surveyed_start,
        start_sigmas=start_sigmas,
        # GPS is drawn in the stop loop's stream above, not a kind's own (below): the published
        # figures of every scenario with GPS stay reproducible
        measurements={"gps": tuple(fixes)},
        wheel_slip=SlipPrior(dr_cfg.wheel_slip_mean, dr_cfg.wheel_slip_bias_sigma),
    )
    truth = GroundTruth(world_T_body=poses, landmarks=landmarks, wheel_slip=float(traverse_slip),
                        terrain=terrain.height,
                        kinds={} if true_rig is None else {"stereo_calibration": true_rig.state(rig)},
                        mast_angles={stop: tuple(angles) for stop, angles in mast_angles.items()})
    return _with_kind_measurements(scenario, traverse, truth, seed)


def kind_rng(seed: int, name: str) -> np.random.Generator:
    """The random stream of a kind's simulated sensor, named after the kind."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def _with_kind_measurements(scenario: Scenario, traverse: Traverse, truth: GroundTruth, seed: int
                            ) -> tuple[Traverse, GroundTruth]:
    """The records of every kind with a simulated sensor (kinds/base.py), each drawn from a random
    stream of its own, named after the kind: adding a kind changes nothing else. The true states
    they drew go into the truth."""
    measurements, true_states = dict(traverse.measurements), dict(truth.kinds)
    for name, kind in KINDS.items():
        sensor = getattr(scenario, name) if kind.Sensor is not None else None
        if sensor is None or not getattr(sensor, "enabled", True):
            continue
        records, state = kind.simulate_with_truth(sensor, traverse, truth, kind_rng(seed, name))
        if records:
            measurements[name] = tuple(records)
        if state:
            true_states[name] = state
    return (dataclasses.replace(traverse, measurements=measurements),
            dataclasses.replace(truth, kinds=true_states))


def _fixes_while_driving(scenario: Scenario, path, stops: list[Stop], stop_s: np.ndarray, frame: LocalFrame,
                         rng: np.random.Generator) -> list:
    """Fixes at the configured rate from the first stop to the last one's departure, wherever the
    rover is then: standing at a stop or driving between two at constant speed."""
    knots_t = np.ravel([[st.time_s, st.departure_s] for st in stops])
    knots_s = np.repeat(stop_s, 2)
    times = np.arange(0.0, knots_t[-1], 1.0 / scenario.gps.rate_hz)
    distances = np.interp(times, knots_t, knots_s)
    keep = np.array([not _in_ranges(d, scenario.gps.dropouts) for d in distances], dtype=bool)
    poses = rover_poses(path, distances[keep])
    return [gps_fix(pose, float(t), scenario.gps, frame, rng) for pose, t in zip(poses, times[keep], strict=True)]
