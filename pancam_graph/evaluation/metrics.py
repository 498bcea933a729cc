"""Trajectory metrics of DESIGN.md section 5: average, closure and relative closure error,
ATE after a stated alignment, KITTI-style drift and the path-length ratio."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

Alignment = Literal["none", "se3", "yaw"]
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
    length_ratio: float  # estimated / reference length (the seed's VO came out short)
    drift_translation_pct: float | None = None  # KITTI-style, mean over segments
    drift_rotation_deg_per_m: float | None = None
    drift_segments_m: list[float] = field(default_factory=list)

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


def align(est: np.ndarray, ref: np.ndarray, kind: Alignment) -> tuple[np.ndarray, str]:
    """Rigidly align est (N, 3) to ref (N, 3); never with scale. Returns the aligned points and
    the alignment applied (a degenerate geometry falls back and says so)."""
    if kind == "none":
        return est, "none"
    if kind == "yaw":
        rot, t = fit_yaw(est, ref)
        return est @ rot.T + t, "yaw"
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    e, r = est - mu_e, ref - mu_r
    cov = r.T @ e / len(est)
    if np.linalg.matrix_rank(cov, tol=1e-9 * max(np.abs(cov).max(), 1e-12)) < 2:
        # Umeyama is degenerate on a straight line: fall back to yaw + translation.
        aligned, _ = align(est, ref, "yaw")
        return aligned, "yaw (se3 degenerate: straight trajectory)"
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    return e @ rot.T + mu_r, "se3"


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
            cos = np.clip((np.trace(err[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            r_err.append(np.degrees(np.arccos(cos)) / length)
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
    ref_len = path_length(ref_positions) if reference_length_m is None else reference_length_m
    est_len = path_length(est_positions)
    drift_t = drift_r = None
    segments: list[float] = []
    if est_poses is not None and ref_poses is not None:
        drift_t, drift_r, segments = kitti_drift(est_poses, ref_poses)
    return TrajectoryMetrics(
        average_error_m=float(err3.mean()),
        average_error_2d_m=float(err2.mean()),
        closure_error_m=float(err3[-1]),
        closure_error_2d_m=float(err2[-1]),
        relative_closure_pct=float(100.0 * err3[-1] / ref_len) if ref_len > 0 else float("nan"),
        ate_rmse_m=ate,
        ate_alignment=applied,
        reference_length_m=float(ref_len),
        estimated_length_m=float(est_len),
        length_ratio=float(est_len / ref_len) if ref_len > 0 else float("nan"),
        drift_translation_pct=drift_t,
        drift_rotation_deg_per_m=drift_r,
        drift_segments_m=segments,
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
