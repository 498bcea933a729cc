"""Wheel odometry + GPS through iSAM2, for recorded drives: one pose per GPS fix, odometry
between consecutive poses, each used fix a robust GPS factor in local ENU.

Every `holdout_every`-th fix stays out of the graph and only scores the result, so the score
is against measurements the estimate never saw.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from .errors import InputError
from .evaluation.metrics import fit_yaw
from .geodesy import LocalFrame
from .graph import factors, noise
from .graph.keys import X
from .graph.smoother import Smoother, poses_array
from .records import GpsFix, OdometryTrack

_ALIGN_DISTANCE_M = 15.0  # odometry travelled before the initial heading is taken from GPS


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel odometry error model (1 sigma). A driver's own odometry covariance is usually a
    constant placeholder, so the model is set here: translation error grows with distance
    (slip), heading error as a random walk in distance plus a fraction of each turn."""

    translation_fraction: float = 0.05
    min_translation_m: float = 0.02
    heading_deg_per_sqrt_m: float = 0.5
    turn_fraction: float = 0.05
    min_heading_deg: float = 0.05
    tilt_deg: float = 1.0  # roll and pitch per step: wheel odometry assumes flat ground
    vertical_fraction: float = 0.1

    def covariance(self, prev_T_curr: gtsam.Pose3) -> np.ndarray:
        d = float(np.linalg.norm(prev_T_curr.translation()))
        turn = abs(prev_T_curr.rotation().yaw())
        yaw = max(np.deg2rad(self.heading_deg_per_sqrt_m) * np.sqrt(d) + self.turn_fraction * turn,
                  np.deg2rad(self.min_heading_deg))
        xy = max(self.translation_fraction * d, self.min_translation_m)
        z = max(self.vertical_fraction * d, self.min_translation_m)
        tilt = np.deg2rad(self.tilt_deg)
        return np.diag(np.array([tilt, tilt, yaw, xy, xy, z]) ** 2)


@dataclass(frozen=True)
class FusionOptions:
    holdout_every: int = 5  # 0: use every fix
    gps_kernel: str = "huber"
    odometry: OdometryNoise = field(default_factory=OdometryNoise)


@dataclass(frozen=True)
class FusionResult:
    origin: LocalFrame
    times_s: np.ndarray  # (N,) one per fix
    world_T_body: np.ndarray  # (N, 4, 4) fused
    odometry_world_T_body: np.ndarray  # (N, 4, 4) odometry alone, aligned (yaw + translation) to the used fixes
    gps_enu: np.ndarray  # (N, 3)
    sigma_horizontal_m: np.ndarray  # (N,) per axis, as stated by each fix
    used: np.ndarray  # (N,) bool: in the graph; the others are held out
    update_ms: np.ndarray  # (N,)

    def holdout_scores(self) -> dict[str, float]:
        """RMS horizontal distance of the fused and odometry-only tracks to the held-out fixes,
        and the fixes' own stated horizontal error as a 2-D RMS (DRMS, sqrt(sigma_e^2 + sigma_n^2):
        what a perfect track would score)."""
        held = ~self.used
        if not held.any():
            raise InputError("no fixes were held out (holdout_every = 0)")

        def rms(points: np.ndarray) -> float:
            return float(np.sqrt(np.mean(np.sum((points[held, :2] - self.gps_enu[held, :2]) ** 2, axis=1))))

        return {
            "held_out_fixes": int(held.sum()),
            "used_fixes": int(self.used.sum()),
            "fused_rms_m": rms(self.world_T_body[:, :3, 3]),
            "odometry_only_rms_m": rms(self.odometry_world_T_body[:, :3, 3]),
            "stated_drms_m": float(np.sqrt(np.mean(2.0 * self.sigma_horizontal_m[held] ** 2))),
        }


def odometry_at(track: OdometryTrack, times_s: np.ndarray) -> list[gtsam.Pose3]:
    """Odometry poses interpolated on SE(3) (geodesic between the bracketing messages) at the given times."""
    idx = np.clip(np.searchsorted(track.times_s, times_s), 1, len(track) - 1)
    poses = []
    for t, j in zip(times_s, idx, strict=True):
        t0, t1 = track.times_s[j - 1], track.times_s[j]
        a = 0.0 if t1 == t0 else float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
        poses.append(gtsam.Pose3(track.odom_T_body[j - 1]).slerp(a, gtsam.Pose3(track.odom_T_body[j])))
    return poses


def fuse_odometry_gps(odometry: OdometryTrack, fixes: list[GpsFix], options: FusionOptions = FusionOptions()
                      ) -> FusionResult:
    fixes = sorted((f for f in fixes if odometry.times_s[0] <= f.time_s <= odometry.times_s[-1]),
                   key=lambda f: f.time_s)
    if len(fixes) < 3:
        raise InputError(f"{odometry.source}: only {len(fixes)} GPS fixes fall inside the odometry's time span")
    origin = LocalFrame(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].h_m)
    times = np.array([f.time_s for f in fixes])
    enu = origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.h_m for f in fixes])
    sigma_h = np.array([f.sigma_horizontal_m for f in fixes])
    used = np.ones(len(fixes), dtype=bool)
    if options.holdout_every > 0:
        used[options.holdout_every - 1:: options.holdout_every] = False

    odom = odometry_at(odometry, times)
    odom_xyz = np.array([p.translation() for p in odom])
    world_T_odom = _initial_alignment(odom_xyz, enu, used)

    smoother = Smoother()
    first = gtsam.Pose3(world_T_odom @ odom[0].matrix())
    start_sigmas = np.array([np.deg2rad(5.0), np.deg2rad(5.0), np.deg2rad(30.0),
                             3 * sigma_h[0], 3 * sigma_h[0], 3 * fixes[0].sigma_vertical_m])
    smoother.add(gtsam.PriorFactorPose3(X(0), first, noise.pose_sigmas(start_sigmas[:3], start_sigmas[3:])))
    smoother.insert(X(0), first)
    for i, fix in enumerate(fixes):
        if i > 0:
            step = odom[i - 1].between(odom[i])
            smoother.add(factors.motion(i - 1, i, step, options.odometry.covariance(step)))
            smoother.insert(X(i), smoother.pose(X(i - 1)).compose(step))
        if used[i]:
            model = noise.robust(options.gps_kernel, noise.gps_position(fix.sigma_horizontal_m, fix.sigma_vertical_m))
            smoother.add(factors.gps(i, enu[i], np.zeros(3), model))
        smoother.update(context=f"at GPS fix {i} (t = {fix.time_s:.3f} s)")
    smoother.settle()
    poses = poses_array(smoother.estimate(), [X(i) for i in range(len(fixes))])

    world_T_odom = np.eye(4)
    world_T_odom[:3, :3], world_T_odom[:3, 3] = fit_yaw(odom_xyz[used], enu[used])
    odometry_only = world_T_odom @ np.stack([p.matrix() for p in odom])
    return FusionResult(origin, times, poses, odometry_only, enu, sigma_h, used, np.asarray(smoother.update_ms))


def _initial_alignment(odom_xyz: np.ndarray, enu: np.ndarray, used: np.ndarray) -> np.ndarray:
    """world_T_odom (4x4) from the first stretch of drive: heading is unobservable before the
    robot has moved, so it is fitted to the used fixes over the first ~15 m."""
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(odom_xyz, axis=0), axis=1))])
    n = int(np.searchsorted(travelled, _ALIGN_DISTANCE_M)) + 1
    first = used.copy()
    first[n:] = False
    if first.sum() < 3:
        first = used
    rot, t = fit_yaw(odom_xyz[first], enu[first])
    world_T_odom = np.eye(4)
    world_T_odom[:3, :3], world_T_odom[:3, 3] = rot, t
    return world_T_odom
