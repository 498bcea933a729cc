"""Site maps as GeoTIFF (orbital/geotiff.py, orbital/maps.py): a DTM of a scenario's
terrain written at 1 m posts opens in rasterio with the map projection's CRS and transform and
gives back the terrain's heights; a map that cannot be used is refused with its file named."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import CRS, Transformer
from rasterio.transform import Affine

from pancam_graph.config import bundled_scenarios, load_scenario
from pancam_graph.errors import InputError
from pancam_graph.geometry.geodesy import LocalFrame
from pancam_graph.orbital.dem_registration import RegistrationFailed, register_site, yaw_of
from pancam_graph.orbital.geotiff import read_map_raster, write_map_raster
from pancam_graph.orbital.maps import ground_spacing, ground_spacing_note, sampled_raster
from pancam_graph.records import MapRaster
from pancam_graph.render.terrain import Ground
from pancam_graph.sim.world import dense_path, landmark_field


@pytest.fixture(scope="module")
def terrain():
    scenario = load_scenario(bundled_scenarios()["short_trail"])
    path = dense_path(scenario.path)
    return scenario, path, Ground(scenario, path, seed=3)


@pytest.mark.parametrize("body", ["earth", "mars"])
def test_a_written_dtm_opens_with_its_crs_and_transform_and_gives_the_terrain_back(terrain, body, tmp_path):
    scenario, path, ground = terrain
    frame = LocalFrame(scenario.origin.lat_deg, scenario.origin.lon_deg, 250.0, body=body)
    centre = path.points[len(path.points) // 2, :2]
    dtm = sampled_raster(ground.height, frame, centre - 60.0, centre + 60.0, 1.0)
    write_map_raster(tmp_path / "dtm.tif", dtm)
    with rasterio.open(tmp_path / "dtm.tif") as written:
        assert CRS.from_wkt(written.crs.to_wkt()) == frame.map_crs()
        assert written.transform == from_origin(dtm.x0_m, dtm.y0_m, 1.0, 1.0) and written.res == (1.0, 1.0)
        assert written.shape == dtm.values.shape and min(written.shape) >= 120 and written.dtypes[0] == "float32"
    back = read_map_raster(tmp_path / "dtm.tif")
    rng = np.random.default_rng(5)
    xy = centre + rng.uniform(-50.0, 50.0, (400, 2))
    enu = np.column_stack([xy, ground.at(xy)[0]])  # the ground, its height along the frame's up
    true = frame.to_geodetic(enu)[:, 2]  # a DTM's height: above the body's surface
    error = back.at(frame.to_map(enu)) - true
    # bilinear between 1 m posts on relief of 0.8 m at wavelengths of 4-30 m: 95 % within 8 mm (a
    # map half a post off would put 95 % within 37 mm). The terrain steps by centimetres where the
    # nearest point of the path changes, which no grid follows: those few make the RMS 1-2 cm.
    assert np.percentile(np.abs(error), 95) < 0.015 and np.sqrt(np.mean(error**2)) < 0.03


def from_origin(west: float, north: float, x_size: float, y_size: float) -> Affine:
    return Affine(x_size, 0.0, west, 0.0, -y_size, north)


def test_at_measurement_level_the_dtm_is_the_ground_the_landmarks_lie_on(terrain):
    """The landmarks scatter about the DTM by the terrain's roughness (rocks a 1 m DTM cannot see)."""
    scenario, path, _ = terrain
    landmarks, ground = landmark_field(path, scenario.terrain, np.random.default_rng(8))
    frame = LocalFrame(scenario.origin.lat_deg, scenario.origin.lon_deg, 0.0, body="mars")
    centre = path.points[len(path.points) // 3, :2]
    dtm = sampled_raster(ground.height, frame, centre - 50.0, centre + 50.0, 1.0)
    near = np.all(np.abs(landmarks[:, :2] - centre) < 45.0, axis=1)
    assert near.sum() > 1000
    residual = frame.to_geodetic(landmarks[near])[:, 2] - dtm.at(frame.to_map(landmarks[near]))
    assert abs(np.mean(residual)) < 0.02
    assert np.std(residual) == pytest.approx(scenario.terrain.roughness_m, rel=0.1)


def _write(path, values, crs="EPSG:32632", transform=None, count=1, dtype="float32"):
    profile = {"driver": "GTiff", "height": values.shape[0], "width": values.shape[1], "count": count,
               "dtype": dtype, "transform": transform or from_origin(456000.0, 5428000.0, 1.0, 1.0)}
    if crs is not None:
        profile["crs"] = crs
    with rasterio.open(path, "w", **profile) as out:
        for band in range(1, count + 1):
            out.write(values.astype(dtype), band)


@pytest.mark.parametrize("values, dtype, message", [
    (np.array([[1.0, np.inf, 2.0], [-np.inf, 3.0, 4.0]]), "float32",
     r"2 infinite heights \(the first at row 0, column 1\): expected finite heights"),
    (np.full((3, 3), np.nan), "float32", r"no height at any post \(all nodata\)"),
    (np.array([[100, 120], [130, 90]]), "int16", r"int16 heights with no nodata value: expected float heights"),
    (np.zeros((4, 4)), "uint8", r"every grey level is 0 \(no data\): an orthoimage with nothing to correlate"),
])
def test_a_map_with_nothing_usable_in_it_is_refused(tmp_path, values, dtype, message):
    """What used to pass the reader: infinite heights (then scipy's 'must not contain infs' deep in
    the registration), an all-nodata DTM, integer heights with no nodata value (read as heights
    of 0 where the map has none), an all-black orthoimage (silently unused)."""
    _write(tmp_path / "map.tif", values, dtype=dtype)
    with pytest.raises(InputError, match=r"map.tif: " + message):
        read_map_raster(tmp_path / "map.tif")


@pytest.mark.parametrize("fault, message", [
    ("no_crs", "no CRS: a map must say where it is"),
    ("geographic", "CRS EPSG:4326 is geographic \\(degrees\\): expected a projected CRS"),
    ("rotated", "rotated pixels"),
    ("oblong", "pixels 1.0 x 2.0 m: expected square"),
    ("two_bands", "2 bands; a DTM or a grey orthoimage has one"),
    ("text", "not a readable GeoTIFF"),
    ("missing", "no such map file"),
])
def test_a_map_that_cannot_be_used_is_refused_with_its_file_named(fault, message, tmp_path):
    path = tmp_path / "map.tif"
    values = np.zeros((4, 5))
    if fault == "no_crs":
        _write(path, values, crs=None)
    elif fault == "geographic":
        _write(path, values, crs="EPSG:4326", transform=from_origin(8.4, 49.0, 1e-5, 1e-5))
    elif fault == "rotated":
        _write(path, values, transform=Affine(1.0, 0.1, 456000.0, 0.1, -1.0, 5428000.0))
    elif fault == "oblong":
        _write(path, values, transform=from_origin(456000.0, 5428000.0, 1.0, 2.0))
    elif fault == "two_bands":
        _write(path, values, count=2)
    elif fault == "text":
        path.write_text("elevation\n1 2 3\n")
    with pytest.raises(InputError, match=f"map.tif: {message}"):
        read_map_raster(path)


def test_nodata_becomes_nan_and_an_orthoimage_keeps_its_grey_levels(tmp_path):
    heights = np.arange(12, dtype=float).reshape(3, 4)
    heights[1, 2] = -9999.0
    profile = {"driver": "GTiff", "height": 3, "width": 4, "count": 1, "dtype": "float32", "crs": "EPSG:32632",
               "transform": from_origin(456000.0, 5428000.0, 1.0, 1.0), "nodata": -9999.0}
    with rasterio.open(tmp_path / "dtm.tif", "w", **profile) as out:
        out.write(heights.astype("float32"), 1)
    dtm = read_map_raster(tmp_path / "dtm.tif")
    assert np.isnan(dtm.values[1, 2]) and dtm.values[2, 3] == 11.0
    assert np.isnan(dtm.at(np.array([[456002.5, 5427998.5]]))[0])  # next to the hole
    ortho = MapRaster(np.arange(20, dtype=np.uint8).reshape(4, 5), 456000.0, 5428000.0, 0.25,
                      CRS.from_epsg(32632).to_wkt())
    write_map_raster(tmp_path / "ortho.tif", ortho)
    back = read_map_raster(tmp_path / "ortho.tif")
    assert back.values.dtype == np.uint8 and np.array_equal(back.values, ortho.values) and back.post_m == 0.25


REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
GALE_DTM = REAL / "gale_dtm_mmgis" / "missionDEM.tif"
needs_gale_dtm = pytest.mark.skipif(not GALE_DTM.is_file(), reason=f"needs {GALE_DTM} (../shared beside the checkout)")


@pytest.mark.real_data
@needs_gale_dtm
def test_a_real_gale_dtm_reads_with_its_east_west_ground_spacing_stated():
    """missionDEM.tif: 1 m posts in an equidistant cylindrical CRS of the Mars 2000 sphere with
    its standard parallel at 0, at 4.67 S: cos(4.667 deg) = 0.99668 m apart east-west on the ground."""
    dtm = read_map_raster(GALE_DTM)
    assert dtm.values.shape == (337, 348) and dtm.post_m == 1.0 and not np.isnan(dtm.values).any()
    assert -4473.5 < np.nanmin(dtm.values) and np.nanmax(dtm.values) < -4437.5
    east, north = ground_spacing(dtm)
    assert east == pytest.approx(np.cos(np.deg2rad(4.6668)), abs=2e-6) and north == pytest.approx(1.0, abs=1e-9)
    assert "0.9967 m apart east-west and 1.0000 m north-south" in ground_spacing_note("missionDEM.tif", dtm)
    assert ground_spacing_note("square", dataclasses.replace(dtm, crs_wkt=_equirectangular_at(-4.6668))) is None


def _equirectangular_at(standard_parallel_deg: float) -> str:
    return CRS.from_proj4(f"+proj=eqc +lat_ts={standard_parallel_deg} +R=3396190 +units=m +no_defs").to_wkt()


def test_ground_spacing_follows_the_latitude_of_a_standard_parallel_at_0():
    """The same 1 m posts placed at 60 N: half a metre east-west on the ground."""
    north_60 = MapRaster(np.zeros((10, 10), np.float32), 0.0, 3396190.0 * np.deg2rad(60.0) + 5.0, 1.0,
                         _equirectangular_at(0.0))
    east, north = ground_spacing(north_60)
    assert east == pytest.approx(0.5, abs=1e-4) and north == pytest.approx(1.0, abs=1e-9)


@pytest.mark.real_data
@needs_gale_dtm
def test_sites_on_the_real_gale_dtm_register_back_to_their_known_offsets():
    """Site point clouds sampled from the real DTM (1,500 points within 25 m, 5 cm of height noise)
    at five spots with relief, predicted 1-3 m and up to 5 deg off: registration finds the true
    pose within 10 cm and 0.2 deg; a spot of low relief (0.6 m RMS over 50 m) is refused as
    ambiguous, as on simulated maps."""
    dtm = read_map_raster(GALE_DTM)
    crs = CRS.from_wkt(dtm.crs_wkt)
    x, y = dtm.centres()
    centre = Transformer.from_crs(crs, crs.geodetic_crs, always_xy=True).transform(x[174], y[168])
    frame = LocalFrame(centre[1], centre[0], -4450.0, body="mars")
    rng = np.random.default_rng(5)
    for row, col in [(80, 260), (170, 170), (250, 100), (250, 260), (120, 200)]:
        site, yaw = _ground_point(dtm, frame, crs, x[col], y[row]), rng.uniform(-np.pi, np.pi)
        points_body, true_T = _site_points(dtm, frame, crs, site, yaw, rng)
        predicted = true_T.copy()
        predicted[:2, 3] += rng.uniform(-3.0, 3.0, 2)
        turn = np.deg2rad(rng.uniform(-5.0, 5.0))
        predicted[:3, :3] = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]) \
            @ predicted[:3, :3]
        found = register_site(points_body, np.full(len(points_body), 0.05**2), predicted, dtm, frame, 6.0)
        error = found.map_T_body[:3, 3] - true_T[:3, 3]
        yaw_error = np.rad2deg((yaw_of(found.map_T_body[:3, :3]) - yaw + np.pi) % (2 * np.pi) - np.pi)
        assert np.hypot(*error[:2]) < 0.1 and abs(error[2]) < 0.05 and abs(yaw_error) < 0.2, (row, col, error)
    site = _ground_point(dtm, frame, crs, x[80], y[80])
    points_body, true_T = _site_points(dtm, frame, crs, site, 0.3, rng)
    with pytest.raises(RegistrationFailed, match="relief is ambiguous"):
        register_site(points_body, np.full(len(points_body), 0.05**2), true_T, dtm, frame, 6.0)


def _ground_point(dtm, frame, crs, x, y) -> np.ndarray:
    return frame.from_map(np.array([[x, y]]), dtm.at(np.array([[x, y]]))[0], crs)[0]


def _site_points(dtm, frame, crs, site, yaw, rng, n=1500):
    """(points in the body frame, world_T_body) of a rover at `site` facing `yaw`: the DTM's ground
    within 25 m, its heights with 5 cm of noise."""
    angle, radius = rng.uniform(0, 2 * np.pi, n), np.sqrt(rng.uniform(1.0, 25.0**2, n))
    around = site + np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(n)])
    xy = frame.to_map(around, crs)
    ground = frame.from_map(xy, dtm.at(xy), crs)
    ground[:, 2] += rng.normal(0.0, 0.05, n)
    world_T_body = np.eye(4)
    world_T_body[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
    world_T_body[:3, 3] = site
    return (ground - site) @ world_T_body[:3, :3], world_T_body


def test_a_crs_whose_text_is_not_utf8_is_refused_by_name(tmp_path):
    """Found by fuzzing: a damaged CRS citation made GDAL hand over bytes that are not UTF-8
    (UnicodeDecodeError from rasterio)."""
    _write(tmp_path / "map.tif", np.ones((4, 4)), crs=CRS.from_user_input("IAU_2015:49910").to_wkt())
    data = (tmp_path / "map.tif").read_bytes()
    at = data.find(b"Mars")
    assert at > 0
    (tmp_path / "map.tif").write_bytes(data[:at] + b"\xff\xcd" + data[at + 2:])
    with pytest.raises(InputError, match=r"map.tif: its CRS's text is not UTF-8"):
        read_map_raster(tmp_path / "map.tif")
