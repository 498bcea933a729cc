"""Results folders: written whole into a staging folder, then renamed into place."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import gtsam
import numpy as np

from ..errors import ResultsError


@contextlib.contextmanager
def results_folder(out: Path) -> Iterator[Path]:
    """Yield a staging folder; on success it becomes `out`, on failure it is kept beside it
    as `<out>.partial` so nothing computed is lost."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ResultsError(f"{out}: results folder exists and is not empty; choose another --out")
    staging = out.with_name(out.name + ".partial")
    if staging.exists():
        shutil.rmtree(staging)
    try:
        staging.mkdir(parents=True)
    except OSError as exc:
        raise ResultsError(f"{staging}: cannot create results folder: {exc.strerror}") from None
    yield staging
    if out.exists():
        out.rmdir()
    os.replace(staging, out)


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n", encoding="utf-8")


def write_tum(path: Path, times_s: np.ndarray, world_T_body: np.ndarray) -> None:
    """TUM trajectory: `time tx ty tz qx qy qz qw` per line."""
    with path.open("w", encoding="utf-8") as f:
        f.write("# time tx ty tz qx qy qz qw (world = local ENU, body = rover)\n")
        for t, m in zip(times_s, world_T_body, strict=True):
            q = gtsam.Rot3(m[:3, :3]).toQuaternion()
            f.write(f"{t:.3f} {m[0, 3]:.6f} {m[1, 3]:.6f} {m[2, 3]:.6f} "
                    f"{q.x():.9f} {q.y():.9f} {q.z():.9f} {q.w():.9f}\n")


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,), world_T_body (N, 4, 4)) from a TUM file."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    poses = np.zeros((len(rows), 4, 4))
    for i, r in enumerate(rows):
        rot = gtsam.Rot3.Quaternion(r[7], r[4], r[5], r[6]).matrix()
        poses[i, :3, :3], poses[i, :3, 3], poses[i, 3, 3] = rot, r[1:4], 1.0
    return rows[:, 0], poses


def write_csv(path: Path, header: list[str], rows) -> None:
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
