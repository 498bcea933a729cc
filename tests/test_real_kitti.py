"""KITTI raw drive 2011_09_26_drive_0001 (images omitted) and a generated KITTI-layout folder."""

import shutil
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.geodesy import LocalFrame
from pancam_graph.io.kitti import read_kitti_raw

DATE = Path(__file__).parent / "data" / "real" / "kitti_raw" / "2011_09_26"
DRIVE = DATE / "2011_09_26_drive_0001_sync"
A, F = 6378137.0, 1.0 / 298.257223563  # WGS84


def _devkit_mercator(lat, lon, scale, radius_north=A, radius_east=A):
    """The KITTI devkit's latlonToMercator with latToScale(lat0); the devkit uses a sphere of
    radius A for both axes, which the radii of curvature of the ellipsoid correct."""
    mx = scale * np.deg2rad(lon) * radius_east
    my = scale * radius_north * np.log(np.tan(np.deg2rad(90.0 + lat) / 2.0))
    return mx, my


def test_oxts_to_enu_agrees_with_an_independent_computation():
    drive = read_kitti_raw(DRIVE)
    lat, lon, alt = (drive.oxts.field(n) for n in ("lat", "lon", "alt"))
    assert len(lat) == 108 and not drive.left_images
    lines = (DRIVE / "oxts" / "timestamps.txt").read_text().split("\n")
    first = datetime.strptime(lines[0][:26], "%Y-%m-%d %H:%M:%S.%f").replace(tzinfo=UTC)
    assert drive.oxts.times_s[0] == pytest.approx(first.timestamp(), abs=1e-6)
    assert np.all(np.diff(drive.oxts.times_s) > 0.09)  # 10 Hz
    enu = LocalFrame(lat[0], lon[0], alt[0]).to_enu(lat, lon, alt)
    length = np.sum(np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1))
    assert length == pytest.approx(107, abs=1.0)
    # Devkit formula with the WGS84 radii of curvature at the first packet (meridian M, prime vertical N)
    e2 = F * (2 - F)
    s = np.sin(np.deg2rad(lat[0]))
    m, n = A * (1 - e2) / (1 - e2 * s * s) ** 1.5, A / np.sqrt(1 - e2 * s * s)
    mx, my = _devkit_mercator(lat, lon, np.cos(np.deg2rad(lat[0])), radius_north=m, radius_east=n)
    independent = np.column_stack([mx - mx[0], my - my[0]])
    assert np.abs(enu[:, :2] - independent).max() < 0.05
    # The devkit's own sphere is 0.2 % off in scale here: about 0.19 m over the drive.
    mx, my = _devkit_mercator(lat, lon, np.cos(np.deg2rad(lat[0])))
    devkit = np.column_stack([mx - mx[0], my - my[0]])
    assert 0.1 < np.linalg.norm(enu[:, :2] - devkit, axis=1).max() < 0.003 * length


def test_stereo_calibration_of_the_date():
    stereo = read_kitti_raw(DRIVE).stereo
    assert stereo.camera.fx == pytest.approx(721.5377) and stereo.camera.cx == pytest.approx(609.5593)
    assert stereo.baseline_m == pytest.approx(0.532725, abs=1e-4)  # KITTI's published 0.54 m rig


def test_reader_loads_images_of_a_generated_kitti_folder(tmp_path):
    date = tmp_path / "2011_09_26"
    drive = date / DRIVE.name
    shutil.copytree(DRIVE / "oxts", drive / "oxts")
    shutil.copy(DATE / "calib_cam_to_cam.txt", date)
    rng = np.random.default_rng(0)
    for cam in ("image_02", "image_03"):
        (drive / cam / "data").mkdir(parents=True)
        for i in range(108):
            cv2.imwrite(str(drive / cam / "data" / f"{i:010d}.png"), rng.integers(0, 255, (37, 124), np.uint8))
    loaded = read_kitti_raw(drive)
    assert len(loaded.left_images) == 108
    left, right = loaded.stereo_pair(5)
    assert left.shape == (37, 124) and left.dtype == np.uint8
    assert np.array_equal(left, cv2.imread(str(drive / "image_02" / "data" / "0000000005.png"), 0))
    (drive / "image_03" / "data" / "0000000107.png").unlink()
    with pytest.raises(InputError, match="108 left .* but 107 right"):
        read_kitti_raw(drive)
    (drive / "oxts" / "data" / "0000000003.txt").write_text("49.0 8.4\n")
    (drive / "image_02" / "data" / "0000000107.png").unlink()
    with pytest.raises(InputError, match=r"0000000003.txt: line 1: expected 30 OXTS fields, got 2"):
        read_kitti_raw(drive)
