"""Trajectory files for evaluation: TUM and KITTI poses, or any GPS log as positions."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from ..errors import InputError
from ..geometry.geodesy import LocalFrame
from ..graph.frozen import pose_matrices
from ..records import Trajectory
from .gps_logs import read_gps_file


def read_trajectory(path: Path, origin: LocalFrame | None = None, gps_sigma_m: float = 1.0) -> Trajectory:
    """TUM (`time tx ty tz qx qy qz qw`) or KITTI (12 numbers per line) poses, told apart by
    the column count; anything else is read as a GPS log and converted to ENU at `origin`
    (the first fix when no origin is given)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    rows = _numeric_rows(path)
    if rows is not None and rows.shape[1] == 8:
        return _tum(path, rows)
    if rows is not None and rows.shape[1] == 12:
        return _kitti(path, rows)
    fixes, _ = read_gps_file(path, gps_sigma_m, gps_sigma_m)
    if not fixes:
        raise InputError(f"{path}: no usable GPS fixes")
    llh = np.array([[f.lat_deg, f.lon_deg, f.h_m] for f in fixes])
    origin = origin or LocalFrame(*llh[0])
    enu = origin.to_enu(llh[:, 0], llh[:, 1], llh[:, 2])
    return Trajectory(str(path), enu, np.array([f.time_s for f in fixes]), None, llh)


def read_tum(path: Path) -> Trajectory:
    """A TUM file (`time tx ty tz qx qy qz qw`), checked: unit quaternions, increasing times."""
    return _tum(Path(path), _table(path, 8, "a TUM trajectory (8 numbers per line: time tx ty tz qx qy qz qw)"))


def read_kitti_poses(path: Path) -> Trajectory:
    """A KITTI pose file (12 numbers per line: the top 3x4 of each pose matrix), checked."""
    return _kitti(Path(path), _table(path, 12, "a KITTI pose file (12 numbers per line: r11 r12 r13 tx ... r33 tz)"))


def _table(path: Path, columns: int, what: str) -> np.ndarray:
    path = Path(path)
    rows = _numeric_rows(path) if path.is_file() else None
    if rows is None or rows.shape[1] != columns:
        raise InputError(f"{path}: not {what}")
    return rows


def _finite(path: Path, rows: np.ndarray) -> None:
    """NaN or inf in a pose file would pass every other check and fail only after a whole run."""
    bad = ~np.all(np.isfinite(rows), axis=1)
    if np.any(bad):
        raise InputError(f"{path}: pose {int(np.argmax(bad)) + 1}: a value that is not a finite number")


def _kitti(path: Path, rows: np.ndarray) -> Trajectory:
    _finite(path, rows)
    poses = pose_matrices(rows)
    _check_rotations(path, poses)
    return Trajectory(str(path), poses[:, :3, 3].copy(), None, poses)


def _numeric_rows(path: Path) -> np.ndarray | None:
    """The file as a float table (comments '#'), or None when it is not one."""
    lines = []
    with path.open(encoding="utf-8", errors="replace") as f:
        for text in f:
            text = text.split("#", 1)[0].strip()
            if text:
                lines.append(text.replace(",", " ").split())
    if not lines or len({len(fields) for fields in lines}) != 1:
        return None
    try:
        return np.array(lines, dtype=float)
    except ValueError:
        return None


def _tum(path: Path, rows: np.ndarray) -> Trajectory:
    _finite(path, rows)
    poses = np.zeros((len(rows), 4, 4))
    for i, r in enumerate(rows):
        q = r[4:8]
        with np.errstate(over="ignore"):  # a norm of 1e308s is inf, and refused below
            norm = np.linalg.norm(q)
        if not 0.99 < norm < 1.01:
            raise InputError(f"{path}: pose {i + 1}: quaternion (qx qy qz qw) has norm {norm:.4f}, expected 1")
        poses[i, :3, :3] = gtsam.Rot3.Quaternion(q[3], q[0], q[1], q[2]).matrix()
        poses[i, :3, 3], poses[i, 3, 3] = r[1:4], 1.0
    if np.any(np.diff(rows[:, 0]) <= 0):
        i = int(np.argmax(np.diff(rows[:, 0]) <= 0))
        raise InputError(f"{path}: pose {i + 2}: time {rows[i + 1, 0]} does not increase")
    return Trajectory(str(path), rows[:, 1:4].copy(), rows[:, 0].copy(), poses)


def _check_rotations(path: Path, poses: np.ndarray) -> None:
    err = np.abs(np.einsum("nji,njk->nik", poses[:, :3, :3], poses[:, :3, :3]) - np.eye(3)).max(axis=(1, 2))
    if np.any(err > 1e-3):
        raise InputError(f"{path}: pose {int(np.argmax(err > 1e-3)) + 1}: rotation is not orthonormal "
                         f"(KITTI rows: r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz)")
