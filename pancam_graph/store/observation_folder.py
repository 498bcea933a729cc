"""The observation-level input format: what an external stereo front-end hands our back-end.

A folder (documented in docs/observation_format.md):

    traverse.toml   name, origin, rig (preset or calibration file), noise, start pose, estimator
    stereo.csv      stop,time_s,track,u_left,u_right,v        navigation stereo pair, rectified px
    panorama.csv    stop,site,pan_rad,tilt_rad,track,u_left,u_right,v   (optional) site panoramas
    hrc.csv         stop,pan_rad,tilt_rad,track,u,v                     (optional) HRC frames
    odometry.csv    stop,r11..r33,tx,ty,tz,c00..c55 (upper triangle)    (optional) dead reckoning
    truth.kitti     (optional) reference pose of every stop, KITTI layout, for evaluation
    truth_landmarks.csv  track,x_m,y_m,z_m (optional, with truth.kitti) true landmarks (ENU)
    truth.toml      wheel_slip = ... (optional, with truth.kitti) the traverse's true slip, and
                    [kinds.<kind>] the true values of kinds' own variables (the map biases)
    maps/*.tif      (optional) orbital maps, DTM and orthoimage GeoTIFFs, listed in the
                    manifest's [[maps]] with their stated accuracy (a real HiRISE DTM too)
    <kind>.csv      (optional) the records of a measurement kind with a table of its own
                    (Kind.columns in pancam_graph/kinds/): gps.csv (time_s,lat_deg,lon_deg,h_m,
                    sigma_h_m,sigma_v_m, each fix used at its time), sun_heading.csv

Stops are numbered 0..N-1 and every stop has at least one row in stereo.csv (a stop that saw
nothing has one row with empty track and pixel fields, so its time is still known); an optional
dwell_s column says how long the rover stood at the stop after its time. Numbers are
written with repr(), so a folder written from a traverse reads back bit for bit.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import EstimatorConfig, load_toml_model
from ..errors import InputError
from ..formats.tables import CsvTable
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import Camera, Rig, rig_preset
from ..kinds import KINDS
from ..kinds.base import RowError
from ..records import (
    DeadReckoning,
    GroundTruth,
    HrcFrame,
    OrbitalMap,
    PanoramaFrame,
    SlipPrior,
    StereoObservations,
    Stop,
    Traverse,
)
from ..runtime.text_files import read_text
from .observation_manifest import (
    COVARIANCE_UPPER,
    FRAME_COLUMNS,
    FRAMES,
    HRC_COLUMNS,
    MANIFEST,
    ODOMETRY_COLUMNS,
    PANORAMA_COLUMNS,
    PANORAMA_FRAME_COLUMNS,
    PANORAMA_FRAMES,
    STEREO_COLUMNS,
    Manifest,
    MapSource,
    PanoramaImage,
    RigSource,
)

if TYPE_CHECKING:
    from ..geometry.stereo_pair import StereoCalibration


@dataclass(frozen=True)
class ObservationSet:
    traverse: Traverse
    truth: GroundTruth | None
    estimator: EstimatorConfig
    seed: int
    source: Path
    frames: list[tuple[Path, Path]] | None = None  # an image folder: left and right image per stop
    panorama_frames: tuple[PanoramaImage, ...] = ()  # an image folder: site panorama and HRC images
    # the rig's calibration as calibrated, when it is a file whose images need rectifying
    calibration: StereoCalibration | None = None
    notes: tuple[str, ...] = ()  # what the reader noticed that the user should hear of (one line each)


def is_observation_folder(path: Path) -> bool:
    return (Path(path) / MANIFEST).is_file() and not is_image_folder(path)


def is_image_folder(path: Path) -> bool:
    """An observation folder whose navigation stereo pairs are images (frames.csv)."""
    return (Path(path) / MANIFEST).is_file() and (Path(path) / FRAMES).is_file()


def read_observations(folder: Path) -> ObservationSet:
    """An observation folder as a traverse (and its reference, when truth.kitti is there)."""
    folder = Path(folder)
    manifest = _manifest(folder / MANIFEST)
    rig, calibration = _rig(folder, manifest.rig)
    frames = None
    panorama_frames: tuple[PanoramaImage, ...] = ()
    if (folder / FRAMES).is_file() and not (folder / "stereo.csv").is_file():
        times, dwells, frames = _read_frames_csv(folder / FRAMES)
        stereo = [StereoObservations.empty()] * len(times)  # the image front-end fills them in
        panorama_frames = _read_panorama_frames(folder / PANORAMA_FRAMES, len(times))
    else:
        times, dwells, stereo = _read_stereo(folder / "stereo.csv", rig.wac)
    n = len(times)
    panoramas, sites = _read_panorama(folder / "panorama.csv", n, rig.wac)
    hrc = _read_hrc(folder / "hrc.csv", n, rig.hrc or rig.wac)
    odometry = _read_odometry(folder / "odometry.csv", n)
    stops = tuple(Stop(k, times[k], stereo[k], sites.get(k), panoramas.get(k, ()), hrc.get(k, ()), odometry.get(k),
                       dwells[k]) for k in range(n))
    o = manifest.origin
    start = np.array(manifest.start_world_T_body, dtype=float)  # 4x4: the manifest model checks shapes
    body_T_left = None
    if manifest.rig.body_T_left is not None:
        body_T_left = np.array(manifest.rig.body_T_left, dtype=float)  # rigid: the manifest model checks it
        body_T_left[:3, :3] = body_T_left[:3, :3] @ rig.rectification()  # body_T_left is the raw camera's
    traverse = Traverse(manifest.name, rig, LocalFrame(o.lat_deg, o.lon_deg, o.h_m, o.body), stops,
                        manifest.traverse_tilt_rad, manifest.image_noise_px,
                        np.array(manifest.gps_lever_arm_m, dtype=float), start, np.array(manifest.start_sigmas),
                        wheel_slip=SlipPrior(manifest.wheel_slip_mean, manifest.wheel_slip_sigma),
                        body_T_nav_left=body_T_left)
    measurements = _read_kind_tables(folder, traverse)
    notes: tuple[str, ...] = ()
    if manifest.maps:
        measurements["orbital"] = _read_maps(folder, manifest.maps)
        notes = _map_notes(folder, manifest.maps, measurements["orbital"], traverse)
    if measurements:
        traverse = dataclasses.replace(traverse, measurements=measurements)
    truth = None
    if (folder / "truth.kitti").is_file():
        landmarks = _read_truth_landmarks(folder / "truth_landmarks.csv")
        slip, states = _read_truth_toml(folder / "truth.toml")
        truth = GroundTruth(_read_truth(folder / "truth.kitti", n), landmarks, slip, kinds=states)
    return ObservationSet(traverse, truth, manifest.estimator, manifest.seed, folder, frames, panorama_frames,
                          None if calibration is None or calibration.is_rectified else calibration, notes)


def _read_kind_tables(folder: Path, traverse: Traverse) -> dict[str, tuple]:
    """Each kind's own table, <kind>.csv, where the folder has one (kinds/base.py)."""
    out = {}
    for name, kind in KINDS.items():
        path = folder / f"{name}.csv"
        if not kind.columns or not path.is_file():
            continue
        table = CsvTable(path, list(kind.columns))
        rows = [(line, tuple(table.number(line, c, v) for c, v in zip(kind.columns, table.values(line, row),
                                                                        strict=True)))
                for line, row in table.rows]
        try:
            records = kind.from_rows(rows, traverse)
        except RowError as exc:
            raise InputError(f"{path}: line {exc.line}: {exc}") from None
        if records:
            out[name] = tuple(records)
    return out


def read_estimator(folder: Path) -> EstimatorConfig:
    """The folder's estimator settings, from its manifest alone (no table read)."""
    return _manifest(Path(folder) / MANIFEST).estimator


def _manifest(path: Path) -> Manifest:
    return load_toml_model(path, Manifest, "observation manifest", InputError)


def _rig(folder: Path, source: RigSource) -> tuple[Rig, StereoCalibration | None]:
    """The rig, and its calibration as calibrated when it is a calibration file."""
    if source.preset is None and source.calibration is None:
        raise InputError(f"{folder / MANIFEST}: [rig] needs a 'preset', a 'calibration' or both")
    preset = None
    if source.preset is not None:
        try:
            preset = rig_preset(source.preset)
        except ValueError as exc:
            raise InputError(f"{folder / MANIFEST}: [rig] preset: {exc}") from None
        if source.calibration is None:
            return preset, None
    from dataclasses import replace

    from ..formats.calibration import read_stereo_calibration

    right = folder / source.calibration_right if source.calibration_right else None
    raw, stereo = read_stereo_calibration(folder / source.calibration, right, source.calibration_image_size)
    rotation = None if raw is None or raw.is_rectified else tuple(stereo.raw_R_rectified.ravel().tolist())
    if source.rectification is not None:
        given = np.array(source.rectification, dtype=float)
        if rotation is not None or not np.allclose(given @ given.T, np.eye(3), atol=1e-6):
            raise InputError(f"{folder / MANIFEST}: [rig] rectification: expected a 3x3 rotation, with a "
                             "calibration that is already rectified")
        rotation = tuple(given.ravel().tolist())
    if preset is not None:
        return replace(preset, wac=stereo.camera, baseline_m=stereo.baseline_m, raw_R_rectified=rotation), raw
    return Rig(source.calibration, stereo.camera, stereo.baseline_m, source.mast_height_m,
               raw_R_rectified=rotation), raw


def _read_stereo(path: Path, camera: Camera) -> tuple[list[float], list[float], list[StereoObservations]]:
    table = CsvTable(path, STEREO_COLUMNS, optional=["dwell_s"])
    table.check_widths()
    lines = table.lines()
    stop = table.integers("stop", 0, _MAX_STOPS, f"stop {{value}} outside 0..{_MAX_STOPS - 1}")
    time_s = table.numbers("time_s")
    first = _first_rows(stop)  # per row, the first row of its stop
    if (bad := _first_true(time_s != time_s[first])) is not None:
        raise InputError(f"{path}: line {lines[bad]}: stop {stop[bad]} has time {float(time_s[bad])}, earlier rows "
                         f"say {float(time_s[first[bad]])}")
    dwell = table.optional_numbers("dwell_s", 0.0)
    if (bad := _first_true((dwell < 0) | (dwell != dwell[first]))) is not None:
        raise InputError(f"{path}: line {lines[bad]}: stop {stop[bad]}: dwell_s must be >= 0 and the same on every "
                         "row")
    # a stop that saw nothing has one row with empty track and pixel fields
    seen = np.array([any(t) for t in zip(*(table.texts(c) for c in ("track", "u_left", "u_right", "v")),
                                         strict=True)], dtype=bool)
    observed = table.where(seen)
    track = observed.tracks()
    if (bad := _first_true(_first_rows(stop[seen], track) != np.arange(len(track)))) is not None:
        raise InputError(f"{path}: line {lines[seen][bad]}: stop {stop[seen][bad]} lists track {track[bad]} a second "
                         "time")
    uvv = np.column_stack([observed.pixels("u_left", camera.width), observed.pixels("u_right", camera.width),
                           observed.pixels("v", camera.height)])
    stops, at = np.unique(stop, return_index=True)
    n = len(stops)
    if n == 0 or stops[-1] != n - 1:
        missing = next(k for k in range(max(n, 1)) if k >= n or stops[k] != k)
        raise InputError(f"{path}: stops must be numbered 0..N-1 with a row each; no row for stop {missing}")
    by_stop = _rows_by_key(stop[seen], n)
    observations = [StereoObservations(track[rows], uvv[rows]) for rows in by_stop]
    ordered, dwells = time_s[at].tolist(), dwell[at].tolist()
    if any(b < a + dwells[k] for k, (a, b) in enumerate(zip(ordered[:-1], ordered[1:], strict=True))):
        k = next(k for k in range(n - 1) if ordered[k + 1] < ordered[k] + dwells[k])
        raise InputError(f"{path}: stop {k + 1} (t = {ordered[k + 1]} s) comes before stop {k} ends "
                         f"(t = {ordered[k]} s + dwell {dwells[k]} s): stop times must increase")
    return ordered, dwells, observations


def _first_rows(*columns: np.ndarray) -> np.ndarray:
    """Per row, the index of the first row with the same value in every one of `columns`."""
    if len(columns[0]) == 0:
        return np.zeros(0, dtype=np.int64)
    keys = np.rec.fromarrays(columns)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)  # stable: first occurrences
    return first[inverse.reshape(-1)]


def _first_true(flags: np.ndarray) -> int | None:
    """The index of the first true flag, None when there is none."""
    return int(np.argmax(flags)) if np.any(flags) else None


def _rows_by_key(key: np.ndarray, n: int) -> list[np.ndarray]:
    """For each key 0..n-1, the rows that have it, in file order."""
    if n == 0:
        return []
    order = np.argsort(key, kind="stable")
    return np.split(order, np.searchsorted(key[order], np.arange(1, n)))


def _read_frames_csv(path: Path) -> tuple[list[float], list[float], list[tuple[Path, Path]]]:
    """An image folder's frames.csv: per stop (0..N-1 in order) its time, dwell and images."""
    table = CsvTable(path, FRAME_COLUMNS)
    times, dwells, frames = [], [], []
    for line, row in table.rows:
        stop, time_s, dwell_s, left, right = table.values(line, row)
        k = int(table.number(line, "stop", stop, integer=True))
        if k != len(times):
            raise InputError(f"{path}: line {line}: stop {k}, expected {len(times)} (stops numbered 0..N-1 in order)")
        t, dwell = table.number(line, "time_s", time_s), table.number(line, "dwell_s", dwell_s)
        if times and t < times[-1] + dwells[-1]:
            raise InputError(f"{path}: line {line}: time_s {t} comes before the previous stop ends")
        times.append(t)
        dwells.append(dwell)
        frames.append((path.parent / left, path.parent / right))
    if not times:
        raise InputError(f"{path}: no frames")
    return times, dwells, frames


def _read_panorama_frames(path: Path, n: int) -> tuple[PanoramaImage, ...]:
    """An image folder's panorama_frames.csv (optional): WAC pairs and HRC frames at sites."""
    if not path.is_file():
        return ()
    table = CsvTable(path, PANORAMA_FRAME_COLUMNS)
    images = []
    for line, row in table.rows:
        stop, site, camera, pan, tilt, left, right = table.values(line, row)
        if camera not in ("wac", "hrc"):
            raise InputError(f"{path}: line {line}: column 'camera': expected wac or hrc, got {camera!r}")
        if not left or (camera == "wac") != bool(right):
            raise InputError(f"{path}: line {line}: a wac frame needs left and right images, an hrc frame "
                             "a left one only")
        images.append(PanoramaImage(table.stop(line, stop, n), int(table.number(line, "site", site, integer=True)),
                                    camera, table.number(line, "pan_rad", pan), table.number(line, "tilt_rad", tilt),
                                    path.parent / left, path.parent / right if right else None))
    return tuple(images)


def _read_frames(table: CsvTable, n: int, measured: list[str], camera: Camera
                 ) -> dict[int, dict[tuple[float, float], tuple]]:
    """Rows grouped by stop and frame (pan_rad, tilt_rad), in file order: per frame the track ids
    and the `measured` pixel columns (u..., v) as an (N, len(measured)) array."""
    table.check_widths()
    stop, pan, tilt, track = table.stops(n), table.numbers("pan_rad"), table.numbers("tilt_rad"), table.tracks()
    repeated = _first_rows(stop, pan, tilt, track)
    if (bad := _first_true(repeated != np.arange(len(stop)))) is not None:
        lines = table.lines()
        raise InputError(f"{table.path}: line {lines[bad]}: track {track[bad]} a second time in the frame at stop "
                         f"{stop[bad]}, pan {pan[bad]:g} rad, tilt {tilt[bad]:g} rad (line {lines[repeated[bad]]}): "
                         "one row per track and frame")
    uv = np.column_stack([table.pixels(c, camera.height if c == "v" else camera.width) for c in measured])
    # each row's frame, numbered in the order the frames first appear
    firsts, frame = np.unique(_first_rows(stop, pan, tilt), return_inverse=True)
    frames: dict[int, dict[tuple[float, float], tuple]] = defaultdict(dict)
    for rows in _rows_by_key(frame, len(firsts)):
        first = rows[0]  # frames in the order they first appear, each one's rows in file order
        frames[int(stop[first])][(float(pan[first]), float(tilt[first]))] = (track[rows], uv[rows])
    return frames


def _read_panorama(path: Path, n: int, camera: Camera
                   ) -> tuple[dict[int, tuple[PanoramaFrame, ...]], dict[int, int]]:
    if not path.is_file():
        return {}, {}
    table = CsvTable(path, PANORAMA_COLUMNS)
    frames = _read_frames(table, n, ["u_left", "u_right", "v"], camera)  # validates every row first
    stop = table.stops(n)
    site = table.integers("site", -2**63, 2**63, "site {value} outside the 64-bit integers")
    first = _first_rows(stop)
    if (bad := _first_true(site != site[first])) is not None:
        lines = table.lines()
        raise InputError(f"{path}: line {lines[bad]}: site {site[bad]}, but line {lines[first[bad]]} puts stop "
                         f"{stop[bad]} at site {site[first[bad]]}: a stop's panorama is of one site")
    return {k: tuple(PanoramaFrame(pan, tilt, StereoObservations(tracks, uvv))
                     for (pan, tilt), (tracks, uvv) in by_frame.items())
            for k, by_frame in frames.items()}, {int(stop[r]): int(site[r]) for r in np.unique(first)}


def _read_hrc(path: Path, n: int, camera: Camera) -> dict[int, tuple[HrcFrame, ...]]:
    if not path.is_file():
        return {}
    frames = _read_frames(CsvTable(path, HRC_COLUMNS), n, ["u", "v"], camera)
    return {k: tuple(HrcFrame(pan, tilt, tracks, uv) for (pan, tilt), (tracks, uv) in by_frame.items())
            for k, by_frame in frames.items()}


def _read_odometry(path: Path, n: int) -> dict[int, DeadReckoning]:
    if not path.is_file():
        return {}
    increments = {}
    for line, k, numbers in CsvTable(path, ODOMETRY_COLUMNS).stops_and_numbers(n):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = np.reshape(numbers[:9], (3, 3)), numbers[9:12]
        cov = np.zeros((6, 6))
        cov[COVARIANCE_UPPER] = numbers[12:]
        cov = cov + np.triu(cov, 1).T
        if np.abs(pose[:3, :3]).max() > 1.0 + 1e-6 or not np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3),
                                                                         atol=1e-6):
            raise InputError(f"{path}: line {line}: r11..r33 is not a rotation matrix")
        if np.abs(pose[:3, 3]).max() > 1e4:
            raise InputError(f"{path}: line {line}: tx, ty, tz: a step of {np.abs(pose[:3, 3]).max():.3g} m between "
                             "stops")
        if np.any(np.linalg.eigvalsh(cov) <= 0):
            raise InputError(f"{path}: line {line}: covariance c00..c55 is not positive definite")
        increments[k] = DeadReckoning(pose, cov)
    return increments


_MAX_TRACK = 10_000_000  # true landmarks are stored densely by track id
_MAX_STOPS = 10_000_000  # a stop number beyond is a typo (and would be allocated for)


def _read_truth_landmarks(path: Path) -> np.ndarray:
    """(M, 3) indexed by track id; NaN for tracks without a true position."""
    if not path.is_file():
        return np.zeros((0, 3))
    table = CsvTable(path, ["track", "x_m", "y_m", "z_m"])
    table.check_widths()
    track = table.integers("track", 0, _MAX_TRACK, f"track {{value}} outside 0..{_MAX_TRACK - 1}")
    xyz = np.column_stack([table.numbers(c) for c in ("x_m", "y_m", "z_m")])
    points = np.full((int(track.max(initial=-1)) + 1, 3), np.nan)
    points[track] = xyz  # a track listed twice: its last row
    return points


def _read_truth_toml(path: Path) -> tuple[float | None, dict[str, dict[str, float]]]:
    """The true slip and the kinds' true states, where the folder has them."""
    if not path.is_file():
        return None, {}
    import tomllib

    try:
        data = tomllib.loads(read_text(path, "truth"))
    except (tomllib.TOMLDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None

    def number(field: str, value) -> float:
        if not isinstance(value, int | float) or isinstance(value, bool) or not abs(value) < 1e6:
            raise InputError(f"{path}: field {field!r}: expected a finite number, got {value!r}")
        return float(value)

    slip = data.get("wheel_slip")
    kinds = data.get("kinds", {})
    if not isinstance(kinds, dict) or not all(isinstance(v, dict) for v in kinds.values()):
        raise InputError(f"{path}: [kinds] must hold one table of numbers per kind")
    states = {k: {name: number(f"kinds.{k}.{name}", v) for name, v in state.items()} for k, state in kinds.items()}
    return (None if slip is None else number("wheel_slip", slip)), states


def _read_truth(path: Path, n: int) -> np.ndarray:
    """Checked as any KITTI pose file (finite, rotations orthonormal), one pose per stop."""
    from ..formats.trajectories import read_kitti_poses

    poses = read_kitti_poses(path).world_T_body
    if len(poses) != n:
        raise InputError(f"{path}: {len(poses)} poses; expected {n} (one per stop)")
    return poses


def _read_maps(folder: Path, sources: list[MapSource]) -> tuple[OrbitalMap, ...]:
    """The manifest's orbital maps, each GeoTIFF checked (orbital/geotiff.py names the file)."""
    from ..orbital.geotiff import read_map_raster

    maps = []
    for source in sources:
        dtm = read_map_raster(folder / source.dtm)
        if dtm.values.dtype == np.uint8:
            raise InputError(f"{folder / source.dtm}: 8-bit grey levels: expected a DTM of heights (float)")
        ortho = None if source.orthoimage is None else read_map_raster(folder / source.orthoimage)
        maps.append(OrbitalMap(source.name, dtm, ortho, source.offset_sigma_m, source.rotation_sigma_deg,
                               source.vertical_sigma_m, str(folder / source.dtm)))
    return tuple(maps)


def _map_notes(folder: Path, sources: list[MapSource], maps: tuple[OrbitalMap, ...],
               traverse: Traverse) -> tuple[str, ...]:
    """A line for each map raster whose posts are not square on the ground, and for each DTM far
    from the start's height."""
    from ..orbital.maps import ground_spacing_note, start_height_note

    notes = []
    for source, orbital_map in zip(sources, maps, strict=True):
        notes.append(ground_spacing_note(str(folder / source.dtm), orbital_map.dtm))
        notes.append(start_height_note(str(folder / source.dtm), orbital_map.dtm, traverse.origin,
                                       traverse.start_world_T_body[:3, 3], orbital_map.vertical_sigma_m))
        if orbital_map.orthoimage is not None:
            notes.append(ground_spacing_note(str(folder / source.orthoimage), orbital_map.orthoimage))
    return tuple(note for note in notes if note)


