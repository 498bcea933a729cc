"""Writing a traverse as an observation folder (the format an external front-end writes;
store/observation_manifest.py lays it out)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import tomli_w

from ..config import EstimatorConfig, OriginConfig
from ..geometry.rig import Rig, rig_preset
from ..kinds import KINDS
from ..records import (
    GroundTruth,
    OrbitalMap,
    Traverse,
)
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
                             *(r(v) for v in cov[COVARIANCE_UPPER])))
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


