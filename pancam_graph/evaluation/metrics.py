"""Trajectory metrics of docs/design.md section 5: average, closure and relative closure error,
ATE after a stated alignment, KITTI-style drift and the path-length ratio."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal

import gtsam
import numpy as np

Alignment = Literal["none", "se3", "yaw"]
GPS_REFERENCE_STEP_M = 20.0  # a GPS track's length is measured through fixes this far apart
RPE_DELTA_M = 10.0  # default distance of the relative pose error
DRIFT_SEGMENTS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


@dataclass(frozen=True)
class TrajectoryMetrics:
    average_error_m: float  # mean 3-D position error over stops
    average_error_2d_m: float  # same, horizontal only
    closure_error_m: float  # 3-D error at the last stop
    closure_error_2d_m: float
    relative_closure_pct: float  # closure_error_m / reference_length_m
    ate_rmse_m: float
    ate_alignment: str  # the alignment actually applied
    reference_length_m: float
    estimated_length_m: float
    length_ratio: float  # estimated / reference length (the dissertation's VO came out short)
    drift_translation_pct: float | None = None  # KITTI-style, mean over segments
    drift_rotation_deg_per_m: float | None = None
    drift_segments_m: list[float] = field(default_factory=list)
    rpe_delta_m: float | None = None  # relative pose error over this much reference path
    rpe_translation_rmse_m: float | None = None
    rpe_rotation_rmse_deg: float | None = None
    rpe_pairs: int = 0
    # every configuration's ATE both ways, comparable across configurations: unaligned (in the
    # frame the start prior fixes) and SE(3)-aligned (the trajectory's shape alone)
    ate_unaligned_rmse_m: float | None = None
    ate_se3_rmse_m: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def path_length(positions: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)))


def fit_yaw(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation about z and translation (rot 3x3, t 3) with rot @ est + t ~ ref."""
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    h = (est - mu_e)[:, :2].T @ (ref - mu_r)[:, :2]
    theta = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot, mu_r - rot @ mu_e


def fit_alignment(est: np.ndarray, ref: np.ndarray, kind: Alignment) -> tuple[np.ndarray, np.ndarray, str]:
    """Rigid transform (rot 3x3, t 3) with rot @ est + t ~ ref in least squares, never with
    scale, and the alignment applied (a degenerate geometry falls back and says so)."""
    if kind == "none":
        return np.eye(3), np.zeros(3), "none"
    if kind == "yaw":
        rot, t = fit_yaw(est, ref)
        return rot, t, "yaw"
    # Umeyama (1991) without scale, as evo computes it.
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    cov = (ref - mu_r).T @ (est - mu_e) / len(est)
    if np.linalg.matrix_rank(cov, tol=1e-9 * max(np.abs(cov).max(), 1e-12)) < 2:
        # Umeyama is degenerate on a straight line: fall back to yaw + translation.
        rot, t = fit_yaw(est, ref)
        return rot, t, "yaw (se3 degenerate: straight trajectory)"
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    return rot, mu_r - rot @ mu_e, "se3"


def fit_similarity_2d(est: np.ndarray, ref: np.ndarray) -> tuple[float, float, np.ndarray] | None:
    """Umeyama's (1991) similarity taking 2-D points est (N, 2) onto ref (N, 2): its rotation
    (rad, anticlockwise), scale, and the residuals (N,) after it; None when degenerate (fewer
    than three points, or all on one point)."""
    if len(est) < 3:
        return None
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    ce, cr = est - mu_e, ref - mu_r
    spread = float(np.mean(np.sum(ce**2, axis=1)))
    if spread <= 1e-12:
        return None
    u, singular, vt = np.linalg.svd(cr.T @ ce / len(est))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(singular) @ d) / spread)
    residuals = np.linalg.norm(scale * ce @ rot.T - cr, axis=1)
    return float(np.arctan2(rot[1, 0], rot[0, 0])), scale, residuals


def align(est: np.ndarray, ref: np.ndarray, kind: Alignment) -> tuple[np.ndarray, str]:
    """est (N, 3) rigidly aligned to ref (N, 3), and the alignment applied."""
    rot, t, applied = fit_alignment(est, ref, kind)
    return est @ rot.T + t, applied


def rotation_angle_deg(rot: np.ndarray) -> float:
    """Angle of a rotation matrix by its log map (arccos of the trace loses small angles).
    GTSAM's, not scipy's Rotation: scipy.spatial would be one more import in every worker."""
    return float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(rot)))))


def relative_pose_error(est: np.ndarray, ref: np.ndarray, delta_m: float, tolerance: float = 0.1
                        ) -> tuple[float | None, float | None, int]:
    """RPE over a fixed travelled distance (TUM RGB-D definition): RMS translation (m) and
    rotation (deg) of E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) over consecutive pairs (i, j) that are
    `delta_m` of reference path apart, from the first pose on (a pair starts where the previous
    one ended). These are evo's (1.38) pairs with `delta_unit=m, all_pairs=False, pairs_from_reference=True`. est, ref:
    (N, 4, 4). Returns (None, None, 0) when the reference is shorter than one pair."""
    ends, travelled = [0], 0.0
    for i in range(1, len(ref)):
        travelled += float(np.linalg.norm(ref[i, :3, 3] - ref[i - 1, :3, 3]))
        if travelled >= delta_m:
            ends.append(i)
            travelled = 0.0
    pairs = list(zip(ends[:-1], ends[1:], strict=True))
    if not pairs:
        return None, None, 0
    t_err, r_err = [], []
    for i, j in pairs:
        err = np.linalg.inv(np.linalg.inv(ref[i]) @ ref[j]) @ (np.linalg.inv(est[i]) @ est[j])
        t_err.append(np.linalg.norm(err[:3, 3]))
        r_err.append(rotation_angle_deg(err[:3, :3]))
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    return rms(t_err), rms(r_err), len(pairs)


def kitti_drift(
    est: np.ndarray, ref: np.ndarray, segments_m: tuple[float, ...] = DRIFT_SEGMENTS_M, step: int = 10
) -> tuple[float | None, float | None, list[float]]:
    """KITTI odometry drift: relative-pose error over path segments of fixed length, as % of
    the length (translation) and deg/m (rotation). est, ref: (N, 4, 4)."""
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1))])
    t_err, r_err, used = [], [], []
    for length in segments_m:
        if dist[-1] < length:
            continue
        used.append(length)
        for i in range(0, len(ref), step):
            j = int(np.searchsorted(dist, dist[i] + length))
            if j >= len(ref):
                break
            d_ref = np.linalg.inv(ref[i]) @ ref[j]
            d_est = np.linalg.inv(est[i]) @ est[j]
            err = np.linalg.inv(d_ref) @ d_est
            t_err.append(np.linalg.norm(err[:3, 3]) / length)
            r_err.append(rotation_angle_deg(err[:3, :3]) / length)
    if not t_err:
        return None, None, []
    return 100.0 * float(np.mean(t_err)), float(np.mean(r_err)), used


def compare(
    est_positions: np.ndarray,
    ref_positions: np.ndarray,
    alignment: Alignment = "none",
    est_poses: np.ndarray | None = None,
    ref_poses: np.ndarray | None = None,
    reference_length_m: float | None = None,
    rpe_delta_m: float = RPE_DELTA_M,
) -> TrajectoryMetrics:
    """Metrics of an estimate against a reference sampled at the same stops.

    Average and closure errors are taken in the common frame without alignment (the start
    pose is known); only the ATE uses `alignment`.
    """
    est_positions = np.asarray(est_positions, dtype=float)
    ref_positions = np.asarray(ref_positions, dtype=float)
    if est_positions.shape != ref_positions.shape or len(est_positions) < 2:
        raise ValueError(f"need matching (N>=2, 3) arrays, got {est_positions.shape} and {ref_positions.shape}")
    err = est_positions - ref_positions
    err3, err2 = np.linalg.norm(err, axis=1), np.linalg.norm(err[:, :2], axis=1)
    aligned, applied = align(est_positions, ref_positions, alignment)
    ate = float(np.sqrt(np.mean(np.sum((aligned - ref_positions) ** 2, axis=1))))
    se3 = ate if applied == "se3" else float(np.sqrt(np.mean(np.sum(
        (align(est_positions, ref_positions, "se3")[0] - ref_positions) ** 2, axis=1))))
    ref_len = path_length(ref_positions) if reference_length_m is None else reference_length_m
    est_len = path_length(est_positions)
    drift_t = drift_r = None
    segments: list[float] = []
    rpe_t = rpe_r = None
    rpe_pairs = 0
    if est_poses is not None and ref_poses is not None:
        drift_t, drift_r, segments = kitti_drift(est_poses, ref_poses)
        rpe_t, rpe_r, rpe_pairs = relative_pose_error(est_poses, ref_poses, rpe_delta_m)
    return TrajectoryMetrics(
        average_error_m=float(err3.mean()),
        average_error_2d_m=float(err2.mean()),
        closure_error_m=float(err3[-1]),
        closure_error_2d_m=float(err2[-1]),
        relative_closure_pct=float(100.0 * err3[-1] / ref_len) if ref_len > 0 else float("nan"),
        ate_rmse_m=ate,
        ate_alignment=applied,
        ate_unaligned_rmse_m=float(np.sqrt(np.mean(err3**2))),
        ate_se3_rmse_m=se3,
        reference_length_m=float(ref_len),
        estimated_length_m=float(est_len),
        length_ratio=float(est_len / ref_len) if ref_len > 0 else float("nan"),
        drift_translation_pct=drift_t,
        drift_rotation_deg_per_m=drift_r,
        drift_segments_m=segments,
        rpe_delta_m=rpe_delta_m if rpe_pairs else None,
        rpe_translation_rmse_m=rpe_t,
        rpe_rotation_rmse_deg=rpe_r,
        rpe_pairs=rpe_pairs,
    )


def decimated_length(positions: np.ndarray, min_step_m: float) -> float:
    """Path length through points at least `min_step_m` apart: a noisy GPS track's length
    without the noise adding up."""
    kept = [positions[0]]
    for p in positions[1:]:
        if np.linalg.norm(p - kept[-1]) >= min_step_m:
            kept.append(p)
    if len(kept) > 1 and not np.array_equal(kept[-1], positions[-1]):
        kept.append(positions[-1])
    return path_length(np.array(kept))
