"""The two-stop stereo bundle adjustment of the VO: the current stop's pose and the matched
points, the previous pose held fixed, solved by Levenberg-Marquardt on the Schur complement.

It is the system GTSAM builds from two `GenericStereoFactor3D`s a point (the previous pose
fixed by a prior, the points eliminated first), written with numpy because its structure is
fixed: one 6-dof pose and a 3x3 block per point. Built in Python factor by factor, GTSAM's
adjustment dominated the VO's time; here every point is one row of a few arrays.
tests/frontend/test_two_stop_adjustment.py holds it to GTSAM's optimum, marginal and residuals.

Frames: points in the previous stop's left camera frame; the pose is the body's prev_T_curr,
perturbed on the right (GTSAM's Pose3 chart: [rotation, translation] in the current body frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..geometry.calibration_error import pixel_shifts

_MAX_ITERATIONS = 15  # as the GTSAM adjustment it replaces
_RELATIVE_DECREASE = 1e-5  # stop when the cost falls by less than this fraction
_LAMBDA0, _LAMBDA_UP, _LAMBDA_DOWN, _LAMBDA_MAX = 1e-5, 10.0, 0.1, 1e5  # GTSAM's LM defaults
_LAMBDA_MIN = 1e-10  # GTSAM's lower bound is 0; this keeps the damping a number
_MIN_DEPTH_M = 1e-6


@dataclass(frozen=True)
class StereoIntrinsics:
    """A rectified pair's pinhole (pixels) and baseline (m)."""

    fx: float
    fy: float
    skew: float
    cx: float
    cy: float
    baseline_m: float

    @staticmethod
    def of(calibration: gtsam.Cal3_S2Stereo) -> StereoIntrinsics:
        return StereoIntrinsics(calibration.fx(), calibration.fy(), calibration.skew(), calibration.px(),
                                calibration.py(), calibration.baseline())

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 3) stereo pixels (u_left, u_right, v)."""
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        u = (self.fx * x + self.skew * y) / z + self.cx
        return np.column_stack([u, u - self.fx * self.baseline_m / z, self.fy * y / z + self.cy])

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """(N, 3, 3): d(u_left, u_right, v) / d(x, y, z)."""
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        J = np.zeros((len(points), 3, 3))
        J[:, 0, 0] = J[:, 1, 0] = self.fx / z
        J[:, 0, 1] = J[:, 1, 1] = self.skew / z
        J[:, 0, 2] = -(self.fx * x + self.skew * y) / z**2
        J[:, 1, 2] = -(self.fx * (x - self.baseline_m) + self.skew * y) / z**2
        J[:, 2, 1] = self.fy / z
        J[:, 2, 2] = -self.fy * y / z**2
        return J


@dataclass(frozen=True)
class TwoStopSolution:
    """The refined prev_T_curr, its 6x6 marginal covariance and calibration sensitivity (None
    when not asked for) and each point's chi-square: the squared whitened residuals of its two
    stereo observations. The sensitivity is d prev_T_curr / d c (6 x 6: the pose's tangent,
    [rotation, translation], against geometry/calibration_error.py's six terms): to first order
    the adjustment, had it known the pair's calibration error c, would have found
    prev_T_curr * Expmap(sensitivity @ c)."""

    prev_T_curr: gtsam.Pose3
    covariance: np.ndarray | None
    point_chi2: np.ndarray
    calibration_sensitivity: np.ndarray | None = None


def adjust_two_stops(prev_px: np.ndarray, curr_px: np.ndarray, points: np.ndarray, guess: gtsam.Pose3,
                     intrinsics: StereoIntrinsics, body_T_left: gtsam.Pose3, pixel_sigma: float,
                     covariance: bool = True) -> TwoStopSolution | None:
    """Refine `guess` (prev_T_curr of the body) and `points` (N, 3, previous left camera frame)
    against their stereo pixels at both stops. None when the system is indeterminate: a point
    behind a camera or one that the two views cannot place."""
    problem = _Problem(prev_px, curr_px, intrinsics, body_T_left)
    now = problem.evaluate(guess, np.array(points, dtype=float))
    if now is None:
        return None
    lam = _LAMBDA0
    for _ in range(_MAX_ITERATIONS):
        system = problem.normal_equations(now)
        while True:
            step = _solve(system, lam)
            trial = None if step is None else problem.evaluate(now.pose.compose(gtsam.Pose3.Expmap(step[0])),
                                                               now.points + step[1])
            if trial is not None and trial.cost <= now.cost:
                break
            if lam >= _LAMBDA_MAX:  # no step lowers the cost: at the optimum as far as it can tell
                if step is None:
                    return None
                trial = now
                break
            lam *= _LAMBDA_UP
        decrease = now.cost - trial.cost
        now = trial
        lam = max(lam * _LAMBDA_DOWN, _LAMBDA_MIN)
        if decrease <= _RELATIVE_DECREASE * now.cost or now.cost < 1e-12:
            break
    cov = sensitivity = None
    if covariance:
        jacobians = problem.jacobians(now)
        system = problem.normal_equations(now, jacobians)
        schur = _schur(system, 0.0)
        if schur is None:
            return None
        try:
            information_inverse = np.linalg.inv(schur[0])
        except np.linalg.LinAlgError:
            return None
        cov = pixel_sigma**2 * information_inverse
        if not np.all(np.isfinite(cov)) or np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) <= 0):
            return None
        sensitivity = problem.calibration_sensitivity(jacobians, system[3] @ schur[2], information_inverse)
    chi2 = (np.sum(now.r0**2, axis=1) + np.sum(now.r1**2, axis=1)) / pixel_sigma**2
    return TwoStopSolution(now.pose, cov, chi2, sensitivity)


@dataclass(frozen=True)
class _Estimate:
    """A pose and points with what the next step needs of them: the points in the current body
    and camera frames, both views' residuals and the cost (pixels squared)."""

    pose: gtsam.Pose3
    points: np.ndarray
    q: np.ndarray
    cam: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    cost: float


class _Problem:
    def __init__(self, prev_px, curr_px, intrinsics: StereoIntrinsics, body_T_left: gtsam.Pose3):
        self.prev_px, self.curr_px, self.intrinsics = prev_px, curr_px, intrinsics
        self.R_B, self.t_B = body_T_left.rotation().matrix(), body_T_left.translation()

    def evaluate(self, pose: gtsam.Pose3, points: np.ndarray) -> _Estimate | None:
        """None when a point is behind either camera."""
        R_T, t_T = pose.rotation().matrix(), pose.translation()
        q = (points @ self.R_B.T + self.t_B - t_T) @ R_T  # R_T^T (body point - t_T)
        cam = (q - self.t_B) @ self.R_B
        if np.any(points[:, 2] <= _MIN_DEPTH_M) or np.any(cam[:, 2] <= _MIN_DEPTH_M):
            return None
        r0 = self.intrinsics.project(points) - self.prev_px
        r1 = self.intrinsics.project(cam) - self.curr_px
        return _Estimate(pose, points, q, cam, r0, r1, float(np.sum(r0 * r0) + np.sum(r1 * r1)))

    def jacobians(self, e: _Estimate) -> tuple[np.ndarray, np.ndarray]:
        """The residuals' Jacobians: the previous view's (n, 3, 3) in the point, the current
        view's (n, 3, 9) in the pose (right perturbation) and the point."""
        n, q = len(e.q), e.q
        J0 = self.intrinsics.jacobian(e.points)  # previous view: the points only
        # current view: d q = [q]x w - v for the right perturbation [w, v] of the pose, and
        # d q = R_T^T R_B d point; the camera point is R_B^T q
        dq = np.zeros((n, 3, 9))
        dq[:, 0, 1], dq[:, 0, 2] = -q[:, 2], q[:, 1]
        dq[:, 1, 0], dq[:, 1, 2] = q[:, 2], -q[:, 0]
        dq[:, 2, 0], dq[:, 2, 1] = -q[:, 1], q[:, 0]
        dq[:, :, 3:6] = -np.eye(3)
        dq[:, :, 6:] = e.pose.rotation().matrix().T @ self.R_B
        return J0, self.intrinsics.jacobian(e.cam) @ (self.R_B.T @ dq)

    def normal_equations(self, e: _Estimate, jacobians: tuple[np.ndarray, np.ndarray] | None = None):
        """Gauss-Newton blocks (unwhitened: one pixel sigma for all): the pose's 6x6 and
        gradient, each point's 3x3 and gradient, and the 6x3 coupling of each point to the pose."""
        J0, J1 = jacobians or self.jacobians(e)
        J1t = J1.transpose(0, 2, 1)
        H1 = J1t @ J1
        g1 = (J1t @ e.r1[:, :, None])[:, :, 0]
        J0t = J0.transpose(0, 2, 1)
        H_pp = J0t @ J0 + H1[:, 6:, 6:]
        g_p = (J0t @ e.r0[:, :, None])[:, :, 0] + g1[:, 6:]
        return H1[:, :6, :6].sum(axis=0), g1[:, :6].sum(axis=0), H_pp, H1[:, :6, 6:], g_p

    def calibration_sensitivity(self, jacobians, W: np.ndarray, information_inverse: np.ndarray) -> np.ndarray:
        """d pose / d c at the optimum: a calibration error c moves every residual by its pixel
        shift C c, and the Gauss-Newton step that takes back is linear in c (the points eliminated
        as in _schur: W = H_xp H_pp^-1, (n, 6, 3))."""
        J0, J1 = jacobians
        i = self.intrinsics
        C0, C1 = pixel_shifts(self.prev_px, i.fx, i.cx, i.cy), pixel_shifts(self.curr_px, i.fx, i.cx, i.cy)
        J1t = J1.transpose(0, 2, 1)
        g_x = (J1t[:, :6] @ C1).sum(axis=0)  # (6, 6): the pose's gradient per unit of each term
        g_p = J0.transpose(0, 2, 1) @ C0 + J1t[:, 6:] @ C1  # (n, 3, 6): each point's
        return -information_inverse @ (g_x - (W @ g_p).sum(axis=0))


def _schur(system, lam: float):
    """The pose's reduced system (points eliminated) with damping `lam`, and the points'
    inverted blocks; None when a point's block is singular."""
    H_xx, g_x, H_pp, H_xp, g_p = system
    try:
        inv_pp = np.linalg.inv(H_pp + lam * np.eye(3) if lam else H_pp)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(inv_pp)):
        return None
    W = H_xp @ inv_pp  # (n, 6, 3)
    S = H_xx + lam * np.eye(6) - (W @ H_xp.transpose(0, 2, 1)).sum(axis=0)
    rhs = g_x - (W @ g_p[:, :, None]).sum(axis=0)[:, 0]
    return S, rhs, inv_pp


def _solve(system, lam: float):
    """The damped Gauss-Newton step (pose tangent, points), or None when it is singular."""
    schur = _schur(system, lam)
    if schur is None:
        return None
    S, rhs, inv_pp = schur
    try:
        d_pose = -np.linalg.solve(S, rhs)
    except np.linalg.LinAlgError:
        return None
    _, _, _, H_xp, g_p = system
    d_points = -(inv_pp @ (g_p + (H_xp.transpose(0, 2, 1) @ d_pose))[:, :, None])[:, :, 0]
    if not (np.all(np.isfinite(d_pose)) and np.all(np.isfinite(d_points))):
        return None
    return d_pose, d_points
