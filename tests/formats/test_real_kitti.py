"""KITTI raw drive 2011_09_26_drive_0001 (images omitted) and a generated KITTI-layout folder."""

import shutil
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.formats.kitti import read_kitti_raw
from pancam_graph.geometry.geodesy import LocalFrame

pytestmark = pytest.mark.real_data

DATE = Path(__file__).parents[1] / "data" / "real" / "kitti_raw" / "2011_09_26"
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


@pytest.mark.parametrize("field,value,says", [
    ("vf", "nan", "vf nan: expected a finite number"),
    ("lat", "95.0", "lat 95: expected -90..90 degrees"),
    ("lon", "-200", "lon -200: expected -180..360 degrees"),
    ("pos_accuracy", "-0.5", "pos_accuracy -0.5: expected 0 or more"),
])
def test_an_impossible_oxts_packet_is_named_with_its_field(tmp_path, field, value, says):
    from pancam_graph.formats.kitti import OXTS_FIELDS, read_oxts

    oxts = tmp_path / "oxts"
    shutil.copytree(DRIVE / "oxts", oxts)
    packet = oxts / "data" / "0000000004.txt"
    fields = packet.read_text().split()
    fields[OXTS_FIELDS.index(field)] = value
    packet.write_text(" ".join(fields) + "\n")
    with pytest.raises(InputError) as refused:
        read_oxts(oxts)
    assert str(refused.value) == f"{packet}: line 1: {says}"


# -- KITTI odometry ------------------------------------------------------------------------------

PAIR = Path(__file__).parents[1] / "data" / "real" / "kitti00_stereo_pair"
# sequence 00's calib.txt, the two lines the reader uses: P0 (left) and P1 (right, P1[0, 3] = -fx * baseline)
CALIB_00 = {
    "P0": [718.856, 0, 607.1928, 0, 0, 718.856, 185.2157, 0, 0, 0, 1, 0],
    "P1": [718.856, 0, 607.1928, -386.1448, 0, 718.856, 185.2157, 0, 0, 0, 1, 0],
}


def _odometry_layout(root: Path, frames: int = 2, calib: dict | None = None) -> Path:
    """`sequences/00` with the real pair repeated, and a made-up straight forward drive in `poses/00.txt`."""
    sequence = root / "sequences" / "00"
    for camera, name in (("image_0", "left.png"), ("image_1", "right.png")):
        (sequence / camera).mkdir(parents=True)
        for i in range(frames):
            shutil.copy(PAIR / name, sequence / camera / f"{i:06d}.png")
    calib = CALIB_00 if calib is None else calib
    (sequence / "calib.txt").write_text("".join(f"{k}: {' '.join(map(str, v))}\n" for k, v in calib.items()))
    (sequence / "times.txt").write_text("".join(f"{0.1036 * i:e}\n" for i in range(frames)))
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text("".join(f"1 0 0 0 0 1 0 0 0 0 1 {0.8 * i}\n" for i in range(frames)))
    return sequence


def test_kitti_odometry_reader_and_the_real_pair_it_loads(tmp_path):
    from pancam_graph.formats.kitti import read_kitti_odometry

    sequence = read_kitti_odometry(_odometry_layout(tmp_path))
    assert len(sequence) == 2 and sequence.times_s[1] == pytest.approx(0.1036)
    assert sequence.stereo.baseline_m == pytest.approx(0.5371657, abs=1e-7)  # the published baseline
    assert (sequence.stereo.camera.width, sequence.stereo.camera.height) == (1241, 376)
    assert sequence.world_T_camera[1, 2, 3] == pytest.approx(0.8)
    left, right = sequence.stereo_pair(1)
    # The pair is rectified: SIFT matches lie on the same row, and the right camera sees them shifted left.
    sift = cv2.SIFT_create(4000)
    (kl, dl), (kr, dr) = sift.detectAndCompute(left, None), sift.detectAndCompute(right, None)
    good = [a for a, b in cv2.BFMatcher().knnMatch(dl, dr, k=2) if a.distance < 0.7 * b.distance]
    ul = np.array([kl[g.queryIdx].pt for g in good])
    ur = np.array([kr[g.trainIdx].pt for g in good])
    assert len(good) > 300 and np.median(np.abs(ul[:, 1] - ur[:, 1])) < 0.5 and np.mean(ul[:, 0] > ur[:, 0]) > 0.98
    # Triangulated with the calibration read, the road below the horizon is a level plane about 1.65 m
    # under the camera (KITTI's published mounting height): checks fx, cy and baseline together.
    cam, b = sequence.stereo.camera, sequence.stereo.baseline_m
    ok = (np.abs(ul[:, 1] - ur[:, 1]) < 1) & (ul[:, 0] - ur[:, 0] > 1) & (ul[:, 1] > 260)
    z = cam.fx * b / (ul[ok, 0] - ur[ok, 0])
    points = np.column_stack([(ul[ok, 0] - cam.cx) * z / cam.fx, (ul[ok, 1] - cam.cy) * z / cam.fy, z])
    normal, height = _ransac_plane(points, tolerance_m=0.05)
    assert abs(normal[1]) > np.cos(np.deg2rad(3))  # y (down) is the plane's normal: the camera is level
    assert height == pytest.approx(1.65, abs=0.15)


def _ransac_plane(points: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, float]:
    rng = np.random.default_rng(0)
    best = np.zeros(len(points), bool)
    for _ in range(500):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) > 1e-9:
            normal /= np.linalg.norm(normal)
            inliers = np.abs((points - a) @ normal) < tolerance_m
            best = inliers if inliers.sum() > best.sum() else best
    centre = points[best].mean(axis=0)
    normal = np.linalg.svd(points[best] - centre)[2][-1]
    return normal, abs(float(normal @ centre))


def test_kitti_odometry_bad_inputs_are_named(tmp_path):
    from pancam_graph.formats.kitti import read_kitti_odometry

    calib = dict(CALIB_00)
    del calib["P1"]
    with pytest.raises(InputError, match=r"calib\.txt: missing field 'P1'"):
        read_kitti_odometry(_odometry_layout(tmp_path / "a", calib=calib))
    sequence = _odometry_layout(tmp_path / "b")
    (sequence / "image_1" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"image_0 and image_1 differ: 000001.png is in only one of them"):
        read_kitti_odometry(sequence)
    (sequence / "image_0" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"image_0: 1 images but 2 lines in times.txt"):
        read_kitti_odometry(sequence)
    sequence = _odometry_layout(tmp_path / "c")
    (tmp_path / "c" / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"00\.txt: 1 poses but 2 frames"):
        read_kitti_odometry(sequence)
    with pytest.raises(InputError, match="not a KITTI odometry sequence"):
        read_kitti_odometry(tmp_path)


def test_timestamps_out_of_order_are_refused_naming_the_line(tmp_path):
    drive = tmp_path / DATE.name / DRIVE.name
    shutil.copytree(DRIVE, drive)
    for calibration in DATE.glob("calib_*.txt"):
        shutil.copy(calibration, drive.parent)
    stamps = drive / "oxts" / "timestamps.txt"
    lines = stamps.read_text().split("\n")
    lines[5], lines[6] = lines[6], lines[5]
    stamps.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"timestamps.txt: line 7: .* does not come after the line before"):
        read_kitti_raw(drive)
