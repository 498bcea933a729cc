"""Recorded drives without stereo observations (a bag's wheel odometry and GPS, a KITTI raw
drive's OXTS): load them, fuse odometry and GPS, and say how well the result fits the fixes
it never saw."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .evaluation.metrics import GPS_REFERENCE_STEP_M, compare, decimated_length
from .fusion import FusionOptions, FusionResult, fuse_odometry_gps
from .geodesy import LocalFrame
from .io.results import local_frame_dict
from .pipeline import percentiles
from .records import GpsFix, OdometryTrack


@dataclass(frozen=True)
class RecordedDrive:
    """What a recording gives the fusion back-end."""

    name: str
    source: str
    odometry: OdometryTrack
    fixes: list[GpsFix]
    rejected_fixes: list[str] = field(default_factory=list)  # reason per fix left out by the reader
    # Independent poses at the odometry times in a given ENU frame (KITTI: the OXTS solution).
    reference_world_T_body: Callable[[LocalFrame], np.ndarray] | None = None
    notes: list[str] = field(default_factory=list)  # assumptions the reader made


def is_bag(path: Path) -> bool:
    path = Path(path)
    return (path.is_file() and path.suffix in (".bag", ".db3", ".mcap")) or (path / "metadata.yaml").is_file()


def is_kitti_drive(path: Path) -> bool:
    return (Path(path) / "oxts" / "timestamps.txt").is_file()


def drive_from_bag(path: Path, gps_topic: str | None = None, odom_topic: str | None = None) -> RecordedDrive:
    """Topics left as None are the bag's only NavSatFix / Odometry topic."""
    from .io.rosbag import read_navsatfix, read_odometry

    fixes, rejected = read_navsatfix(path, gps_topic)
    return RecordedDrive(Path(path).stem, str(path), read_odometry(path, odom_topic), fixes, rejected,
                         notes=[f"{gps_topic or 'NavSatFix'}: altitude taken as ellipsoidal height",
                                f"{odom_topic or 'Odometry'}: wheel odometry with the distance-based noise model "
                                "(the driver's covariance is not used)"])


def drive_from_kitti(folder: Path, geoid_height_m: float = 0.0) -> RecordedDrive:
    from .io.kitti import read_kitti_raw

    drive = read_kitti_raw(folder)
    return RecordedDrive(Path(folder).name, str(folder), drive.velocity_odometry(), drive.gps_fixes(geoid_height_m),
                         reference_world_T_body=lambda origin: drive.world_T_body(origin, geoid_height_m),
                         notes=["odometry: OXTS body velocities and rates integrated packet to packet",
                                f"GPS: OXTS positions, height = alt + {geoid_height_m} m geoid height, "
                                "sigma = pos_accuracy horizontally, twice that vertically"])


def fuse_drive(drive: RecordedDrive, options: FusionOptions = FusionOptions()) -> FusionResult:
    if not drive.fixes:
        raise InputError(f"{drive.source}: no usable GPS fixes ({len(drive.rejected_fixes)} rejected)")
    return fuse_odometry_gps(drive.odometry, drive.fixes, options)


def fusion_metrics_document(drive: RecordedDrive, result: FusionResult, options: FusionOptions) -> dict:
    """metrics.json of a recorded drive: each track against the held-out fixes (never in the
    graph) and against all fixes, with the run's metric fields."""
    held = ~result.used

    def versus(poses: np.ndarray, mask: np.ndarray) -> dict | None:
        if mask.sum() < 2:
            return None
        ref = result.gps_enu[mask]
        return compare(poses[mask, :3, 3], ref, "none",
                       reference_length_m=decimated_length(ref, GPS_REFERENCE_STEP_M)).as_dict()

    configs = {}
    for name, poses in (("odometry_gps", result.world_T_body), ("odometry", result.odometry_world_T_body)):
        configs[name] = {"vs_held_out_gps": versus(poses, held), "vs_gps": versus(poses, np.ones_like(held))}
    configs["odometry"]["alignment"] = "yaw + translation fitted to the used fixes"
    return {
        "source": drive.source,
        "kind": "recorded drive: wheel odometry + GPS",
        "gps_fixes": len(result.times_s),
        "gps_fixes_rejected_by_reader": len(drive.rejected_fixes),
        "holdout_every": options.holdout_every,
        "holdout": result.holdout_scores() if held.any() else None,
        "origin": local_frame_dict(result.origin),
        "notes": drive.notes,
        "configs": configs,
        "timing": {"isam2_update_ms": percentiles(result.update_ms)},
    }
