"""Results folders: written whole into a staging folder, then renamed into place."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from ..errors import FolderInUse, GeodesyError, InputError, ResultsError, WriteFailed
from ..formats.export import write_trajectory_exports
from ..formats.localization import localization, write_localization
from ..formats.tables import write_csv, write_json
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera, Rig
from ..kinds import STEP_COUNTERS
from .documents import evaluation_document, metrics_document, reproduce_command, run_configuration

if TYPE_CHECKING:
    from ..solve.results import RunResult


LOCK_FILE = ".lock"  # in a staging folder: locked (flock) by the run that owns it, which writes its PID


@contextlib.contextmanager
def results_folder(out: Path, resume: bool = False) -> Iterator[Path]:
    """Yield a staging folder that this run owns exclusively; on success it becomes `out`, on
    failure it is kept beside it as `<out>.partial` so nothing computed is lost.

    Ownership is a kernel lock on the staging folder's lock file, which dies with its process
    (a kill -9 included). A new run creates the staging folder atomically (mkdir), so of two runs
    started on one `--out` exactly one gets it; the other fails at once with FolderInUse. A
    `.partial` left by an earlier run that died is kept, renamed `<out>.partial.<n>`, unless
    `resume`: then this run takes that folder over and goes on in it."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ResultsError(f"{out}: results folder exists and is not empty; choose another --out")
    staging = out.with_name(out.name + ".partial")
    if resume:
        if not staging.is_dir():
            raise ResultsError(f"{staging}: no such folder: nothing to resume")
        lock = _lock(staging, out)
    else:
        _set_aside_dead_partial(staging, out)
        lock = _create_locked(staging, out)
    try:
        yield staging
    finally:  # done or failed, this run no longer owns it (a failed run's folder stays as .partial)
        os.close(lock)
    try:
        (staging / LOCK_FILE).unlink(missing_ok=True)
        if out.exists():
            out.rmdir()  # empty (checked above): the rename below takes its place
        os.replace(staging, out)
    except OSError as exc:
        raise ResultsError(f"{out}: cannot move the finished results into place ({exc.strerror}); "
                           f"they are complete in {staging}") from None


def refuse_if_in_use(out: Path) -> None:
    """FolderInUse now if a live run holds `out`'s staging folder (before a run spends minutes
    reading its source only to be refused then)."""
    staging = Path(out).with_name(Path(out).name + ".partial")
    if (staging / LOCK_FILE).is_file():
        os.close(_lock(staging, Path(out)))


def _create_locked(staging: Path, out: Path) -> int:
    """Create the staging folder already locked: made and locked under a private name, then
    renamed into place, which fails if another run's (never empty) folder is there."""
    private = staging.with_name(f"{staging.name}.new-{os.getpid()}")
    try:
        staging.parent.mkdir(parents=True, exist_ok=True)
        private.mkdir()
    except OSError as exc:
        raise ResultsError(f"{staging}: cannot create results folder: {exc.strerror}") from None
    try:
        lock = _lock(private, out, shown=staging)
    except ResultsError:  # a full disk: nothing of this run stays behind
        shutil.rmtree(private, ignore_errors=True)
        raise
    try:
        os.rename(private, staging)
    except OSError:
        os.close(lock)
        shutil.rmtree(private, ignore_errors=True)
        raise FolderInUse(f"{out}: in use by another run ({staging} exists); choose another --out") from None
    return lock


def _lock(staging: Path, out: Path, shown: Path | None = None) -> int:
    """Lock the staging folder for this process (FolderInUse if a live run holds it); messages
    name it `shown` (the name it is about to take)."""
    try:
        fd = os.open(staging / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise ResultsError(f"{staging}: cannot create its lock file: {exc.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        owner = os.read(fd, 32).decode("ascii", "replace").strip() or "?"
        os.close(fd)
        raise FolderInUse(f"{out}: in use by run {owner} ({staging}); choose another --out") from None
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    except OSError as exc:
        os.close(fd)
        lock_file = (shown or staging) / LOCK_FILE
        raise WriteFailed(f"{lock_file}: cannot write the run's lock file: {exc.strerror}") from None
    return fd


def _set_aside_dead_partial(staging: Path, out: Path) -> None:
    """A staging folder that a live run holds means the folder is in use; one whose owner died is
    renamed out of the way, never deleted."""
    if not staging.exists():
        return
    os.close(_lock(staging, out))  # raises if a live run holds it
    n = 1
    while staging.with_name(f"{staging.name}.{n}").exists():
        n += 1
    staging.rename(staging.with_name(f"{staging.name}.{n}"))


LOCAL_FRAME_FILE = "local_frame.json"  # the ENU origin of every trajectory in a results folder


def local_frame_dict(origin: LocalFrame, gps_lever_arm_m: np.ndarray | None = None) -> dict:
    frame = {"lat_deg": origin.lat0_deg, "lon_deg": origin.lon0_deg, "h_m": origin.h0_m,
             "frame": "local ENU (east, north, up) tangent at this WGS84 point, ellipsoidal height"}
    if origin.body != "earth":
        frame["body"] = origin.body
        frame["frame"] = (f"local ENU (east, north, up) tangent at this point of the IAU 2015 {origin.body} sphere "
                          "(planetocentric latitude, east longitude), height above the sphere")
    if gps_lever_arm_m is not None:  # where a GPS log's positions are on the body (eval uses it)
        frame["gps_lever_arm_m"] = [float(v) for v in gps_lever_arm_m]
    return frame


def _local_frame_file(folder: Path) -> tuple[Path, dict] | None:
    path = Path(folder) / LOCAL_FRAME_FILE
    if not path.is_file():
        return None
    try:
        return path, json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ResultsError(f"{path}: not JSON: {exc}") from None


def read_local_frame(folder: Path) -> LocalFrame | None:
    """The origin saved beside a results folder's trajectories, if there is one."""
    found = _local_frame_file(folder)
    if found is None:
        return None
    path, d = found
    try:
        return LocalFrame(float(d["lat_deg"]), float(d["lon_deg"]), float(d["h_m"]), d.get("body", "earth"))
    except (ValueError, KeyError, TypeError, GeodesyError) as exc:
        raise ResultsError(f"{path}: expected lat_deg, lon_deg, h_m (and body: earth or mars): {exc}") from None


def read_gps_lever_arm(folder: Path) -> np.ndarray | None:
    """The GPS antenna in the body frame saved beside a results folder's trajectories, if any."""
    path, d = _local_frame_file(folder) or (None, {})
    arm = d.get("gps_lever_arm_m") if isinstance(d, dict) else None
    if arm is None:  # a folder from before the arm was saved: the body origin
        return None
    try:
        return np.array([float(v) for v in arm]).reshape(3)
    except (ValueError, TypeError) as exc:
        raise ResultsError(f"{path}: gps_lever_arm_m must be three numbers (x, y, z metres): {exc}") from None


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
    from ..formats.trajectories import read_tum as read_tum_trajectory

    trajectory = read_tum_trajectory(path)
    return trajectory.times_s, trajectory.world_T_body


# -- a run's results folder -----------------------------------------------------------------

# then every kind's per-stop counters (kinds.STEP_COUNTERS); a reader needs only these
STEP_COLUMNS = ["config", "stop", "update_ms", "relinearized"]
# Per stop, for plotting error against distance: the estimate (east, north, up in the local
# frame), the distance driven to it (along the truth, else the estimate), its horizontal error
# against the truth (none without one) and its horizontal 1-sigma (DRMS) and vertical sigma
ESTIMATE_COLUMNS = ["distance_m", "east_m", "north_m", "up_m", "error_2d_m", "sigma_2d_m", "sigma_up_m"]
GPS_COLUMNS = ["time_s", "lat_deg", "lon_deg", "h_m", "sigma_h_m", "sigma_v_m", "used_in_graph"]  # h: ellipsoidal
RUN_FILE = "run.toml"  # the complete resolved configuration of the run
COVARIANCE_COLUMNS = ["stop", "cxx", "cxy", "cxz", "cyy", "cyz", "czz"]
_UPPER = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])


def _estimate_cells(world_T_body: np.ndarray, covariance: np.ndarray, truth: np.ndarray | None) -> list[tuple]:
    """ESTIMATE_COLUMNS' cells of each stop."""
    along = world_T_body if truth is None else truth
    distance = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(along[:, :3, 3], axis=0), axis=1))])
    position = world_T_body[:, :3, 3]
    error = (np.full(len(position), np.nan) if truth is None
             else np.linalg.norm(position[:, :2] - truth[:, :2, 3], axis=1))
    sigma_2d = np.sqrt(np.maximum(covariance[:, 0, 0] + covariance[:, 1, 1], 0.0))
    sigma_up = np.sqrt(np.maximum(covariance[:, 2, 2], 0.0))
    return [(f"{d:.3f}", *(f"{v:.4f}" for v in p), "" if np.isnan(e) else f"{e:.4f}", f"{s2:.4f}", f"{sz:.4f}")
            for d, p, e, s2, sz in zip(distance, position, error, sigma_2d, sigma_up, strict=True)]


def write_evaluation(evaluation, name: str, folder: Path) -> None:
    """`eval`'s metrics.json, in the run's layout."""
    write_json(folder / "metrics.json", evaluation_document(evaluation, name))


def write_run(result: RunResult, folder: Path) -> None:
    """Everything a run computed, as plain files (docs/outputs.md)."""
    import tomli_w

    from ..config import dump_scenario

    stops = result.traverse.stops
    times = np.array([s.time_s for s in stops])
    (folder / RUN_FILE).write_text(tomli_w.dumps(run_configuration(result)), encoding="utf-8")
    if result.scenario is not None:
        (folder / "scenario.toml").write_text(dump_scenario(result.scenario), encoding="utf-8")
    write_json(folder / "metrics.json", metrics_document(result))
    if result.truth is not None:
        write_tum(folder / "truth.tum", times, result.truth.world_T_body)
        np.save(folder / "truth_landmarks.npy", result.truth.landmarks.astype(np.float32))
    fixes = sorted([(f, 1) for f in result.traverse.gps_fixes] + [(f, 0) for f in result.held_out_fixes],
                   key=lambda fu: fu[0].time_s)
    write_csv(folder / "gps_fixes.csv", GPS_COLUMNS,
              [(f"{f.time_s:.6f}", f"{f.lat_deg:.10f}", f"{f.lon_deg:.10f}", f"{f.h_m:.4f}", f.sigma_horizontal_m,
                f.sigma_vertical_m, used) for f, used in fixes])
    write_csv(folder / "motions.csv", ["stop", "source", "vo_inliers", "vo_failure", "translation_m"],
              [(k, m.source, m.vo_inliers, m.vo_failure, f"{np.linalg.norm(m.prev_T_curr.translation()):.6f}")
               for k, m in enumerate(result.motions) if m is not None])
    write_csv(folder / "panoramas.csv", ["stop", "site_id", "camera", "pan_deg", "tilt_deg"],
              [(s.index, s.site_id, camera, f"{np.rad2deg(f.pan_rad):.6f}", f"{np.rad2deg(f.tilt_rad):.6f}")
               for s in stops if s.is_site
               for camera, frames in (("wac", s.panorama), ("hrc", s.hrc)) for f in frames])
    rows = []
    for name, c in result.configurations.items():
        write_tum(folder / f"trajectory_{name}.tum", times, c.world_T_body)
        write_csv(folder / f"covariance_{name}.csv", COVARIANCE_COLUMNS,
                  [(s.index, *(f"{v:.9g}" for v in cov[_UPPER])) for s, cov in zip(stops, c.position_covariance,
                                                                                 strict=True)])
        sites_of: dict[int, list[int]] = {}
        for track, stop in c.tie_links.tolist():
            sites_of.setdefault(track, []).append(stop)
        write_csv(folder / f"landmarks_{name}.csv", ["track", "x_m", "y_m", "z_m", "site_stops"],
                  [(int(t), *(f"{v:.6f}" for v in p), " ".join(map(str, sites_of.get(int(t), []))))
                   for t, p in zip(c.landmark_ids, c.landmark_positions, strict=True)])
        estimates = _estimate_cells(c.world_T_body, c.position_covariance,
                                    None if result.truth is None else result.truth.world_T_body)
        rows += [(name, s.stop, f"{s.update_ms:.4f}", s.relinearized, *(_cell(s.count(c)) for c in STEP_COUNTERS),
                  *cells) for s, cells in zip(c.steps, estimates, strict=True)]
    write_csv(folder / "steps.csv", STEP_COLUMNS + list(STEP_COUNTERS) + ESTIMATE_COLUMNS, rows)
    write_json(folder / LOCAL_FRAME_FILE, local_frame_dict(result.traverse.origin, result.traverse.gps_lever_arm_m))
    (folder / "reproduce.sh").write_text(f"#!/bin/sh\n# reproduces this run\n{reproduce_command(result)}\n",
                                         encoding="utf-8")
    for name, c in result.configurations.items():
        write_trajectory_exports(folder, f"trajectory_{name}", result.traverse.origin if result.source.georeferenced
                                 else None, times, c.world_T_body)
    if result.source.georeferenced and result.traverse.origin.body != "earth":  # Earth has WGS84's files
        counters = np.array(result.source.stop_counters or site_drive_of(stops), dtype=int)
        for name, c in result.configurations.items():
            write_localization(folder, localization(name, result.traverse.origin, times, c.world_T_body,
                                                    c.position_covariance, counters))


def site_drive_of(stops) -> list[tuple[int, int]]:
    """A motion counter for stops that have none: the site is the last panorama stop's site id
    (0 before the first), the drive the stops since it."""
    out, site, since = [], 0, 0
    for stop in stops:
        if stop.is_site:
            site, since = stop.site_id, stop.index
        out.append((site, stop.index - since))
    return out


@dataclass(frozen=True)
class SavedConfiguration:
    name: str
    world_T_body: np.ndarray  # (N, 4, 4)
    position_covariance: np.ndarray  # (N, 3, 3)
    update_ms: np.ndarray  # (N,)
    relinearized: np.ndarray  # (N,)
    counts: dict[str, np.ndarray]  # (N,) each kind's per-stop counter in steps.csv, by name (NaN: none)
    landmark_ids: np.ndarray  # (M,)
    landmark_positions: np.ndarray  # (M, 3)
    tie_links: np.ndarray  # (K, 2) int: (track, site stop)


@dataclass(frozen=True)
class SavedRun:
    """A results folder read back (what `pancam-graph view` replays)."""

    folder: Path
    name: str
    rig: Rig
    body_T_nav: np.ndarray  # 4x4, the navigation pair's left camera in the body frame
    origin: LocalFrame
    run: dict  # run.toml
    metrics: dict
    stops: np.ndarray  # (N,)
    times_s: np.ndarray  # (N,)
    truth_world_T_body: np.ndarray | None
    truth_landmarks: np.ndarray | None
    configurations: dict[str, SavedConfiguration]
    motion_translation_m: np.ndarray  # (N,), 0 at the first stop
    vo_inliers: np.ndarray  # (N,), -1 where there is no motion
    bridged: list[tuple[int, str, str]]  # (stop, source, VO failure)
    gps_times_s: np.ndarray  # (G,)
    gps_lat_lon_h: np.ndarray  # (G, 3)
    gps_used: np.ndarray  # (G,) bool: in the graph (else held out)
    departures_s: np.ndarray  # (N,) each stop's time plus its dwell
    panoramas: list[tuple[int, int, str, float, float]]  # (stop, site id, camera, pan deg, tilt deg)


def read_run(folder: Path) -> SavedRun:
    import tomllib

    folder = Path(folder)
    if not folder.is_dir():
        raise ResultsError(f"{folder}: not a results folder (no such directory)")
    try:
        run = tomllib.loads(_need(folder / RUN_FILE).read_text(encoding="utf-8"))
        r = run["rig"]
        camera = Camera(r["fx"], r["fy"], r["cx"], r["cy"], int(r["width"]), int(r["height"]))
        rig = Rig(r["name"], camera, float(r["baseline_m"]), float(r["mast_height_m"]))
        body_T_nav = np.array(r["body_T_nav_left"], dtype=float).reshape(4, 4)
        departures = np.array(run["stops"]["departure_s"], dtype=float)
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
        raise ResultsError(f"{folder / RUN_FILE}: not a run configuration written by pancam-graph ({exc})") from None
    origin = read_local_frame(folder)
    if origin is None:
        raise ResultsError(f"{folder / LOCAL_FRAME_FILE}: missing from the results folder")
    try:
        metrics = json.loads(_need(folder / "metrics.json").read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ResultsError(f"{folder / 'metrics.json'}: line {exc.lineno}: not JSON ({exc.msg})") from None
    names = list(metrics.get("configs", {}))
    if not names:
        raise ResultsError(f"{folder / 'metrics.json'}: no 'configs' entry")
    truth_path = folder / "truth.tum"
    truth = _read_tum_checked(truth_path)[1] if truth_path.exists() else None
    landmarks_path = folder / "truth_landmarks.npy"
    truth_landmarks = np.load(landmarks_path).astype(float) if landmarks_path.exists() else None

    steps = _read_csv(folder / "steps.csv", STEP_COLUMNS)
    steps_counters = [c for c in (steps[0].keys() if steps else ()) if c not in STEP_COLUMNS + ESTIMATE_COLUMNS]
    configurations = {}
    times = None
    for name in names:
        times, poses = _read_tum_checked(folder / f"trajectory_{name}.tum")
        cov_rows = _read_csv(folder / f"covariance_{name}.csv", COVARIANCE_COLUMNS)
        cov = np.zeros((len(cov_rows), 3, 3))
        for i, row in enumerate(cov_rows):
            cov[i][_UPPER] = [row.number(c) for c in COVARIANCE_COLUMNS[1:]]
            cov[i] = np.triu(cov[i]) + np.triu(cov[i], 1).T
        mine = [r for r in steps if r["config"] == name]
        lm_rows = _read_csv(folder / f"landmarks_{name}.csv", ["track", "x_m", "y_m", "z_m", "site_stops"])
        ids = np.array([int(r.number("track")) for r in lm_rows], dtype=np.int64)
        links = np.array([(int(r.number("track")), int(s)) for r in lm_rows for s in r["site_stops"].split()],
                         dtype=np.int64).reshape(-1, 2)
        configurations[name] = SavedConfiguration(
            name=name,
            world_T_body=poses,
            position_covariance=cov,
            update_ms=np.array([r.number("update_ms") for r in mine]),
            relinearized=np.array([r.number("relinearized") for r in mine]),
            counts={c: np.array([r.number(c) if r.get(c, "") != "" else np.nan for r in mine])
                    for c in steps_counters},
            landmark_ids=ids,
            landmark_positions=np.array([[r.number(c) for c in ("x_m", "y_m", "z_m")] for r in lm_rows]).reshape(-1, 3),
            tie_links=links,
        )
        for what, n in (("covariance", len(cov)), ("steps.csv rows", len(mine))):
            if n != len(poses):
                raise ResultsError(f"{folder}: {name}: {what} has {n} stops, the trajectory {len(poses)}")
    n = len(times)
    translation, inliers, bridged = np.zeros(n), np.full(n, -1), []
    for r in _read_csv(folder / "motions.csv", ["stop", "source", "vo_inliers", "vo_failure", "translation_m"]):
        k = int(r.number("stop"))
        translation[k], inliers[k] = r.number("translation_m"), int(r.number("vo_inliers"))
        if r["source"] != "vo":
            bridged.append((k, r["source"], r["vo_failure"]))
    gps = _read_csv(folder / "gps_fixes.csv", GPS_COLUMNS)
    panoramas = [(int(r.number("stop")), int(r.number("site_id")), r["camera"], r.number("pan_deg"),
                  r.number("tilt_deg"))
                 for r in _read_csv(folder / "panoramas.csv", ["stop", "site_id", "camera", "pan_deg", "tilt_deg"])]
    return SavedRun(
        folder=folder, name=str(metrics.get("scenario", folder.name)), rig=rig, body_T_nav=body_T_nav,
        origin=origin, run=run, metrics=metrics, stops=np.arange(n), times_s=times,
        truth_world_T_body=truth, truth_landmarks=truth_landmarks, configurations=configurations,
        motion_translation_m=translation, vo_inliers=inliers, bridged=bridged,
        gps_times_s=np.array([r.number("time_s") for r in gps]),
        gps_lat_lon_h=np.array([[r.number("lat_deg"), r.number("lon_deg"), r.number("h_m")]
                                for r in gps]).reshape(-1, 3),
        gps_used=np.array([r["used_in_graph"] == "1" for r in gps], dtype=bool),
        departures_s=departures,
        panoramas=panoramas,
    )


class _Row(dict):
    """A CSV row that names its file and line when a value is not a number."""

    path: Path
    line: int

    def number(self, column: str) -> float:
        try:
            return float(self[column])
        except ValueError:
            raise ResultsError(f"{self.path}: line {self.line}: column '{column}': expected a number, "
                               f"got {self[column]!r}") from None


def _need(path: Path) -> Path:
    if not path.exists():
        raise ResultsError(f"{path}: missing from the results folder")
    return path


def _cell(value: float | None) -> str:
    if value is None:
        return ""
    return str(value) if isinstance(value, int) else f"{value:.4f}"


def _read_csv(path: Path, columns: list[str]) -> list[_Row]:
    with _need(path).open(encoding="utf-8", newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise ResultsError(f"{path}: line 1: missing column(s) {', '.join(missing)}")
        rows = []
        for row in reader:
            r = _Row(row)
            r.path, r.line = path, reader.line_num
            rows.append(r)
    return rows


def _read_tum_checked(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        return read_tum(_need(path))
    except InputError as exc:
        raise ResultsError(str(exc)) from None
