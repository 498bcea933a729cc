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

import csv
import dataclasses
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import tomli_w
from pydantic import AfterValidator, Field

from ..config import EstimatorConfig, OriginConfig, _Strict, load_toml_model
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

if TYPE_CHECKING:
    from ..geometry.stereo_pair import StereoCalibration

MANIFEST = "traverse.toml"
FRAMES = "frames.csv"  # an image folder: the navigation stereo pair's images per stop
FRAME_COLUMNS = ["stop", "time_s", "dwell_s", "left", "right"]
PANORAMA_FRAMES = "panorama_frames.csv"  # an image folder: site panorama and HRC images
PANORAMA_FRAME_COLUMNS = ["stop", "site", "camera", "pan_rad", "tilt_rad", "left", "right"]
STEREO_COLUMNS = ["stop", "time_s", "track", "u_left", "u_right", "v"]
PANORAMA_COLUMNS = ["stop", "site", "pan_rad", "tilt_rad", "track", "u_left", "u_right", "v"]
HRC_COLUMNS = ["stop", "pan_rad", "tilt_rad", "track", "u", "v"]
_UPPER = np.triu_indices(6)
ODOMETRY_COLUMNS = (["stop"] + [f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)] + ["tx", "ty", "tz"]
                    + [f"c{i}{j}" for i, j in zip(*_UPPER, strict=True)])


LeverArm = Annotated[float, Field(ge=-10.0, le=10.0)]
Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
Matrix4 = tuple[tuple[float, float, float, float], tuple[float, float, float, float],
                tuple[float, float, float, float], tuple[float, float, float, float]]
Sigma = Annotated[float, Field(gt=0.0, le=1e4)]
RIGID_TOLERANCE = 1e-6  # of R'R against identity (orthonormal axes have det +-1: its sign is checked)
MAX_TRANSLATION_M = 1e6  # as every coordinate in metres of a scenario (config.Metres)


def _rigid(matrix: Matrix4) -> Matrix4:
    """A 4x4 that is a rigid transform: a rotation (orthonormal, det +1), a translation, and
    the last row 0 0 0 1."""
    m = np.array(matrix, dtype=float)
    if not np.all(np.isfinite(m)):
        raise ValueError("not finite")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise ValueError(f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    rotation = m[:3, :3]
    if np.abs(m[:3, 3]).max() > MAX_TRANSLATION_M:
        raise ValueError(f"its translation {m[:3, 3].tolist()} lies beyond {MAX_TRANSLATION_M:g} m")
    if np.abs(rotation).max() > 1.0 + RIGID_TOLERANCE:  # and R'R would overflow on 1e308
        raise ValueError(f"its 3x3 part is not a rotation (an entry of {np.abs(rotation).max():.3g}): expected "
                         "orthonormal axes with det +1")
    off = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    with np.errstate(all="ignore"):  # subnormal entries (1e-320) warn in the LU of det
        det = float(np.linalg.det(rotation))
    if off > RIGID_TOLERANCE or det < 0.0:
        raise ValueError(f"its 3x3 part is not a rotation (R'R differs from identity by {off:.3g}, det "
                         f"{det:.3g}): expected orthonormal axes with det +1")
    return matrix


RigidTransform = Annotated[Matrix4, AfterValidator(_rigid)]


class RigSource(_Strict):
    """A rig preset, or a stereo calibration file on a mast of the given height, or both: the
    preset's mast and HRC with the calibrated navigation pair."""

    preset: str | None = None
    calibration: str | None = Field(None, description="OpenCV YAML, Kalibr camchain, MATLAB stereoParameters .mat "
                                    "or left camera_info")
    calibration_right: str | None = Field(None, description="right camera_info (with a camera_info left)")
    calibration_image_size: tuple[int, int] | None = Field(
        None, description="width, height px: for a MATLAB calibration that does not record it")
    mast_height_m: float = Field(1.5, gt=0.0, le=20.0)
    body_T_left: RigidTransform | None = Field(
        None, description="4x4: the navigation pair's left camera in the body frame, for a body-fixed pair "
        "(default: on the mast at pan 0 and traverse_tilt_rad)")
    rectification: Matrix3 | None = Field(
        None, description="3x3: a rectified calibration's left camera axes in the camera as mounted (the "
        "transpose of stereoRectify's R1), when the images were rectified before the calibration was written")


class MapSource(_Strict):
    """An orbital map of the traverse's ground: GeoTIFFs (paths relative to the folder) and the
    accuracy its producer states for its georeference."""

    name: str = Field(min_length=1)
    dtm: str = Field(description="DTM GeoTIFF: heights above the body's reference surface, a projected CRS")
    orthoimage: str | None = Field(None, description="orthoimage GeoTIFF, one grey band, the DTM's CRS")
    offset_sigma_m: float = Field(3.0, gt=0.0, le=10000.0, description="1-sigma horizontal georeference error, "
                                  "per axis")
    vertical_sigma_m: float = Field(1.0, gt=0.0, le=10000.0, description="1-sigma offset of its heights")
    rotation_sigma_deg: float = Field(0.02, gt=0.0, le=10.0, description="1-sigma rotation about the origin")


class Manifest(_Strict):
    name: str
    seed: int = Field(0, description="seeds the tie-point selection at sites")
    origin: OriginConfig
    rig: RigSource
    image_noise_px: float = Field(gt=0.0, le=50.0)
    traverse_tilt_rad: float = Field(ge=-1.5708, le=1.5708, description="mast tilt of the navigation stereo pair "
                                     "(pan 0)")
    gps_lever_arm_m: tuple[LeverArm, LeverArm, LeverArm] = (0.0, 0.0, 0.0)
    start_world_T_body: RigidTransform = Field(description="4x4, surveyed start pose in local ENU")
    start_sigmas: tuple[Sigma, Sigma, Sigma, Sigma, Sigma, Sigma] = Field(
        description="rotation rad x3, position m x3 (1 sigma)")
    wheel_slip_mean: float = Field(0.0, ge=-0.5, le=1.0, description="expected odometry slip shared along the "
                                   "traverse")
    wheel_slip_sigma: float = Field(0.05, gt=0.0, le=1.0, description="its uncertainty (1 sigma)")
    estimator: EstimatorConfig = EstimatorConfig()
    maps: list[MapSource] = Field(default_factory=list, description="orbital maps (the orbital kind)")


@dataclass(frozen=True)
class PanoramaImage:
    """One image frame of a site panorama (a WAC stereo pair) or an HRC frame, at mast angles."""

    stop: int
    site: int
    camera: str  # "wac" (left and right) or "hrc" (left only)
    pan_rad: float
    tilt_rad: float
    left: Path
    right: Path | None = None


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


# -- writing -------------------------------------------------------------------------------------

def write_observations(folder: Path, traverse: Traverse, estimator: EstimatorConfig, seed: int,
                       truth: GroundTruth | None = None, rig_preset_name: str | None = None,
                       frames: list[tuple[str, str]] | None = None,
                       panorama_frames: list[PanoramaImage] = (), calibration: StereoCalibration | None = None
                       ) -> None:
    """A traverse as an observation folder (the format an external front-end writes); with
    `frames` (left and right image paths per stop, relative to the folder) an image folder:
    frames.csv instead of the observations, panorama_frames.csv for the site images, and
    `calibration` (the navigation pair as calibrated, raw images) beside the rig preset."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    from ..geometry.rig import RIG_PRESETS

    rig = traverse.rig
    preset = rig_preset_name or rig.name
    body_T_left = None
    if traverse.body_T_nav_left is not None:  # the manifest holds the camera as mounted
        body_T_left = traverse.body_T_nav_left.copy()
        body_T_left[:3, :3] = body_T_left[:3, :3] @ rig.rectification().T
    rig_source = RigSource(preset=preset, mast_height_m=rig.mast_height_m,
                           body_T_left=None if body_T_left is None else body_T_left.tolist())
    if calibration is not None:  # raw images: the preset's mast with the pair as calibrated
        from ..formats.calibration import write_opencv_yaml

        write_opencv_yaml(folder / "calibration.yaml", calibration)
        rig_source = rig_source.model_copy(update={"calibration": "calibration.yaml"})
    elif preset not in RIG_PRESETS or rig != rig_preset(preset):
        # a calibrated pair (alone, or on a preset's mast): its rectified model as OpenCV YAML,
        # and the turn rectification gave the left camera
        _write_rectified_yaml(folder / "calibration.yaml", rig)
        rotation = None if rig.raw_R_rectified is None else tuple(map(tuple, rig.rectification().tolist()))
        rig_source = rig_source.model_copy(update={"preset": preset if preset in RIG_PRESETS else None,
                                                   "calibration": "calibration.yaml", "rectification": rotation})
    manifest = Manifest(
        name=traverse.name, seed=seed,
        origin=OriginConfig(lat_deg=traverse.origin.lat0_deg, lon_deg=traverse.origin.lon0_deg,
                            h_m=traverse.origin.h0_m, body=traverse.origin.body),
        rig=rig_source,
        image_noise_px=traverse.image_noise_px, traverse_tilt_rad=traverse.traverse_tilt_rad,
        gps_lever_arm_m=tuple(float(v) for v in traverse.gps_lever_arm_m),
        start_world_T_body=traverse.start_world_T_body.tolist(),
        start_sigmas=tuple(float(v) for v in traverse.start_sigmas), wheel_slip_mean=traverse.wheel_slip.mean,
        wheel_slip_sigma=traverse.wheel_slip.sigma, estimator=estimator,
        maps=_write_maps(folder, traverse.measurements.get("orbital", ())))
    (folder / MANIFEST).write_text(tomli_w.dumps(manifest.model_dump(mode="json", exclude_none=True)),
                                   encoding="utf-8")
    def r(x) -> str:  # shortest text that reads back to the same float
        return repr(float(x))

    stereo, panorama, hrc, odometry = [], [], [], []
    for s in traverse.stops:
        obs = s.stereo
        stereo += [(s.index, r(s.time_s), r(s.dwell_s), int(t), r(a), r(b), r(c))
                   for t, (a, b, c) in zip(obs.track_ids, obs.uvv, strict=True)]
        if not len(obs):
            stereo.append((s.index, r(s.time_s), r(s.dwell_s), "", "", "", ""))
        for f in s.panorama:
            panorama += [(s.index, s.site_id, r(f.pan_rad), r(f.tilt_rad), int(t), r(a), r(b), r(c))
                         for t, (a, b, c) in zip(f.observations.track_ids, f.observations.uvv, strict=True)]
        for f in s.hrc:
            hrc += [(s.index, r(f.pan_rad), r(f.tilt_rad), int(t), r(u), r(v))
                    for t, (u, v) in zip(f.track_ids, f.uv, strict=True)]
        if s.dead_reckoning is not None:
            m, cov = s.dead_reckoning.prev_T_curr, s.dead_reckoning.covariance
            odometry.append((s.index, *(r(v) for v in m[:3, :3].ravel()), *(r(v) for v in m[:3, 3]),
                             *(r(v) for v in cov[_UPPER])))
    if frames is None:
        _write_csv(folder / "stereo.csv", STEREO_COLUMNS[:2] + ["dwell_s"] + STEREO_COLUMNS[2:], stereo)
    else:
        _write_csv(folder / FRAMES, FRAME_COLUMNS, [(s.index, r(s.time_s), r(s.dwell_s), left, right)
                                                   for s, (left, right) in zip(traverse.stops, frames, strict=True)])
    tables = [("odometry.csv", ODOMETRY_COLUMNS, odometry),
              (PANORAMA_FRAMES, PANORAMA_FRAME_COLUMNS,
               [(f.stop, f.site, f.camera, r(f.pan_rad), r(f.tilt_rad), f.left, f.right or "")
                for f in panorama_frames])]
    if frames is None:  # an image folder's panoramas are images (panorama_frames.csv)
        tables += [("panorama.csv", PANORAMA_COLUMNS, panorama), ("hrc.csv", HRC_COLUMNS, hrc)]
    for name, kind in KINDS.items():  # the tables of kinds with records of their own
        if kind.columns and traverse.measurements.get(name):
            tables.append((f"{name}.csv", list(kind.columns),
                           [tuple(r(v) for v in row) for row in kind.to_rows(traverse.measurements[name])]))
    for name, columns, rows in tables:
        if rows:
            _write_csv(folder / name, columns, rows)
    if truth is not None:
        np.savetxt(folder / "truth.kitti", truth.world_T_body[:, :3, :].reshape(-1, 12), fmt="%.17g")
        # what the bound (CRLB) of a configuration with landmarks or a slip variable needs
        seen = [] if frames is not None else sorted({int(t) for s in traverse.stops for f in s.panorama
                                                     for t in f.observations.track_ids})
        seen = [t for t in seen if t < len(truth.landmarks)]
        _write_csv(folder / "truth_landmarks.csv", ["track", "x_m", "y_m", "z_m"],
                   [(t, *(r(v) for v in truth.landmarks[t])) for t in seen])
        states = {k: {name: float(v) for name, v in state.items()} for k, state in truth.kinds.items()}
        truth_toml = ({"wheel_slip": truth.wheel_slip} if truth.wheel_slip is not None else {}) | (
            {"kinds": states} if states else {})
        if truth_toml:
            (folder / "truth.toml").write_text(tomli_w.dumps(truth_toml), encoding="utf-8")


def _write_maps(folder: Path, maps: tuple[OrbitalMap, ...]) -> list[MapSource]:
    """Each orbital map's GeoTIFFs in maps/, and its manifest entry."""
    from ..orbital.geotiff import write_map_raster

    out = []
    for orbital_map in maps:
        (folder / "maps").mkdir(exist_ok=True)
        dtm = f"maps/{orbital_map.name}_dtm.tif"
        write_map_raster(folder / dtm, orbital_map.dtm)
        ortho = None
        if orbital_map.orthoimage is not None:
            ortho = f"maps/{orbital_map.name}_orthoimage.tif"
            write_map_raster(folder / ortho, orbital_map.orthoimage)
        out.append(MapSource(name=orbital_map.name, dtm=dtm, orthoimage=ortho,
                             offset_sigma_m=orbital_map.offset_sigma_m, vertical_sigma_m=orbital_map.vertical_sigma_m,
                             rotation_sigma_deg=orbital_map.rotation_sigma_deg))
    return out


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
                               source.vertical_sigma_m))
    return tuple(maps)


def _map_notes(folder: Path, sources: list[MapSource], maps: tuple[OrbitalMap, ...]) -> tuple[str, ...]:
    """A line for each map raster whose posts are not square on the ground."""
    from ..orbital.maps import ground_spacing_note

    notes = []
    for source, orbital_map in zip(sources, maps, strict=True):
        notes.append(ground_spacing_note(str(folder / source.dtm), orbital_map.dtm))
        if orbital_map.orthoimage is not None:
            notes.append(ground_spacing_note(str(folder / source.orthoimage), orbital_map.orthoimage))
    return tuple(note for note in notes if note)


def _write_rectified_yaml(path: Path, rig: Rig) -> None:
    """A rectified pair as OpenCV FileStorage YAML: identical cameras, no distortion, the right
    one `baseline` along x."""
    from ..formats.calibration import write_opencv_yaml
    from ..geometry.stereo_pair import StereoCalibration

    k = rig.wac.matrix()
    size = (rig.wac.width, rig.wac.height)
    write_opencv_yaml(path, StereoCalibration(str(path), k, np.zeros(5), k, np.zeros(5), size, np.eye(3),
                                              np.array([-rig.baseline_m, 0.0, 0.0])))


def _write_csv(path: Path, header: list[str], rows: list) -> None:
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


# -- reading -------------------------------------------------------------------------------------

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
        notes = _map_notes(folder, manifest.maps, measurements["orbital"])
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

    from ..formats.calibration import read_camera_info_pair, read_raw_calibration

    right = folder / source.calibration_right if source.calibration_right else None
    raw = read_raw_calibration(folder / source.calibration, right, source.calibration_image_size)
    stereo = read_camera_info_pair(folder / source.calibration, right) if raw is None else raw.rectified()
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
    times: dict[int, float] = {}
    dwells: dict[int, float] = {}
    rows: dict[int, dict[int, list[float]]] = defaultdict(dict)  # stop: track: (u_left, u_right, v)
    lines: dict[tuple[int, int], int] = {}  # (stop, track): its line
    for line, row in table.rows:
        stop, time_s, track, ul, ur, v = table.values(line, row)
        k = int(table.number(line, "stop", stop, integer=True))
        if not 0 <= k < _MAX_STOPS:
            raise InputError(f"{path}: line {line}: stop {k} outside 0..{_MAX_STOPS - 1}")
        t = table.number(line, "time_s", time_s)
        if times.setdefault(k, t) != t:
            raise InputError(f"{path}: line {line}: stop {k} has time {t}, earlier rows say {times[k]}")
        dwell = table.optional_number(line, row, "dwell_s", 0.0)
        if dwell < 0 or dwells.setdefault(k, dwell) != dwell:
            raise InputError(f"{path}: line {line}: stop {k}: dwell_s must be >= 0 and the same on every row")
        if track == "" and ul == "" and ur == "" and v == "":
            continue
        track = table.track(line, track)
        if lines.setdefault((k, track), line) != line:
            raise InputError(f"{path}: line {line}: stop {k} lists track {track} a second time")
        rows[k][track] = [table.pixel(line, "u_left", ul, camera.width), table.pixel(line, "u_right", ur, camera.width),
                          table.pixel(line, "v", v, camera.height)]
    n = len(times)
    missing = next((k for k in range(max(n, 1)) if k not in times), None)
    if missing is not None:
        raise InputError(f"{path}: stops must be numbered 0..N-1 with a row each; no row for stop {missing}")
    observations = [StereoObservations(np.array(list(rows[k]), dtype=np.int64),
                                       np.array(list(rows[k].values()), dtype=float).reshape(-1, 3))
                    for k in range(n)]
    ordered = [times[k] for k in range(n)]
    if any(b < a + dwells[k] for k, (a, b) in enumerate(zip(ordered[:-1], ordered[1:], strict=True))):
        k = next(k for k in range(n - 1) if ordered[k + 1] < ordered[k] + dwells[k])
        raise InputError(f"{path}: stop {k + 1} (t = {ordered[k + 1]} s) comes before stop {k} ends "
                         f"(t = {ordered[k]} s + dwell {dwells[k]} s): stop times must increase")
    return ordered, [dwells[k] for k in range(n)], observations


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
    grouped: dict[int, dict[tuple[float, float], dict[int, list]]] = defaultdict(dict)  # stop: frame: track: uv
    lines: dict[tuple[int, float, float, int], int] = {}  # (stop, pan, tilt, track): its line (as _read_stereo)
    for line, row in table.rows:
        values = dict(zip(table.columns, table.values(line, row), strict=True))
        k = table.stop(line, values["stop"], n)
        key = (table.number(line, "pan_rad", values["pan_rad"]), table.number(line, "tilt_rad", values["tilt_rad"]))
        track = table.track(line, values["track"])
        first = lines.setdefault((k, *key, track), line)
        if first != line:
            raise InputError(f"{table.path}: line {line}: track {track} a second time in the frame at stop {k}, "
                             f"pan {key[0]:g} rad, tilt {key[1]:g} rad (line {first}): one row per track and frame")
        grouped[k].setdefault(key, {})[track] = [
            table.pixel(line, c, values[c], camera.height if c == "v" else camera.width) for c in measured]
    return {k: {key: (np.array(list(rows), dtype=np.int64),
                      np.array(list(rows.values()), dtype=float).reshape(-1, len(measured)))
                for key, rows in frames.items()}
            for k, frames in grouped.items()}


def _read_panorama(path: Path, n: int, camera: Camera
                   ) -> tuple[dict[int, tuple[PanoramaFrame, ...]], dict[int, int]]:
    if not path.is_file():
        return {}, {}
    table = CsvTable(path, PANORAMA_COLUMNS)
    frames = _read_frames(table, n, ["u_left", "u_right", "v"], camera)  # validates every row first
    sites: dict[int, tuple[int, int]] = {}  # stop: (site, first line)
    for line, row in table.rows:
        k, site = int(row[table.index[0]]), int(table.number(line, "site", row[table.index[1]], integer=True))
        first_site, first_line = sites.setdefault(k, (site, line))
        if site != first_site:
            raise InputError(f"{path}: line {line}: site {site}, but line {first_line} puts stop {k} at site "
                             f"{first_site}: a stop's panorama is of one site")
    return {k: tuple(PanoramaFrame(pan, tilt, StereoObservations(tracks, uvv))
                     for (pan, tilt), (tracks, uvv) in by_frame.items())
            for k, by_frame in frames.items()}, {k: site for k, (site, _) in sites.items()}


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
        cov[_UPPER] = numbers[12:]
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
    rows = []
    for line, row in table.rows:
        track, x, y, z = table.values(line, row)
        t = int(table.number(line, "track", track, integer=True))
        if not 0 <= t < _MAX_TRACK:
            raise InputError(f"{path}: line {line}: track {t} outside 0..{_MAX_TRACK - 1}")
        rows.append((t, table.number(line, "x_m", x), table.number(line, "y_m", y), table.number(line, "z_m", z)))
    points = np.full((max((r[0] for r in rows), default=-1) + 1, 3), np.nan)
    for t, *p in rows:
        points[t] = p
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
