"""The orbital kind: the simulated map against the terrain it was made of, each site's
registration against the truth, the map bias the graph finds against the drawn one, and every
bad map refused or reported by name."""

import dataclasses
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
import rasterio
from pyproj import CRS

from pancam_graph.config import SimulationErrors, load_scenario, resolve_scenario
from pancam_graph.errors import InputError
from pancam_graph.geometry.calibration_error import NAMES as CALIBRATION_TERMS
from pancam_graph.graph.tie_gate import site_point_cloud
from pancam_graph.kinds.orbital import BIAS_NAMES, _map_pose, predicted_measurement
from pancam_graph.kinds.stereo_calibration import StereoCalibration
from pancam_graph.orbital.dem_registration import DtmErrors, RegistrationFailed, register_site
from pancam_graph.orbital.geotiff import read_map_raster, write_map_raster
from pancam_graph.orbital.maps import MapBias
from pancam_graph.records import MapRaster
from pancam_graph.sim import simulate
from pancam_graph.solve.pipeline import RunOptions, run
from pancam_graph.store.observation_folder import read_observations
from pancam_graph.store.observation_writer import write_observations

ORBITAL = "vo+sites+orbital"


@pytest.fixture(scope="module")
def mars_scenario():
    """mars_traverse cut to two legs (~330 m, 7-10 sites), its orthoimage at 1 m, on the ideal
    simulator (the registration's figures below were measured there)."""
    scenario = load_scenario(resolve_scenario("mars_traverse"), errors="ideal")
    path = scenario.path.model_copy(update={"waypoints": [[0.0, 0.0, 0.0], [200.0, 10.0, 2.0], [200.0, 130.0, 4.0]],
                                            "sharp_turns": [1]})
    return scenario.model_copy(update={
        "name": "mars_two_legs", "path": path,
        "terrain": scenario.terrain.model_copy(update={"featureless": []}),
        "orbital": scenario.orbital.model_copy(update={"orthoimage_pixel_m": 1.0})})


@pytest.fixture(scope="module")
def mars_traverse(mars_scenario):
    return simulate(mars_scenario, 1)  # a map 4.4 m off


def _true_bias(truth) -> np.ndarray:
    return np.array([truth.kinds["orbital"][f"map0_{n}"] for n in BIAS_NAMES])


def test_the_written_dtm_opens_in_rasterio_and_is_the_terrain_seen_through_the_drawn_bias(mars_traverse, mars_scenario,
                                                                                         tmp_path):
    traverse, truth = mars_traverse
    write_observations(tmp_path, traverse, mars_scenario.estimator, 7, truth)
    frame = traverse.origin
    with rasterio.open(tmp_path / "maps" / "orbital_map_dtm.tif") as dtm_file:
        assert CRS.from_wkt(dtm_file.crs.to_wkt()) == frame.map_crs() and dtm_file.res == (1.0, 1.0)
    with rasterio.open(tmp_path / "maps" / "orbital_map_orthoimage.tif") as ortho_file:
        assert ortho_file.dtypes[0] == "uint8" and ortho_file.crs == dtm_file.crs
    read = read_observations(tmp_path)
    assert read.truth.kinds == truth.kinds
    dtm = read.traverse.measurements["orbital"][0].dtm
    bias = _true_bias(truth)
    rng = np.random.default_rng(1)
    ground = truth.positions[rng.integers(0, len(truth.positions), 300), :2] + rng.uniform(-20, 20, (300, 2))
    true_h = truth.terrain(ground)
    shown = MapBias(bias[0], bias[1], bias[3]).to_map(ground)
    enu = np.column_stack([shown, true_h])
    heights = dtm.at(frame.to_map(enu)) - bias[2] - frame.to_geodetic(enu)[:, 2] + true_h
    unbiased = dtm.at(frame.to_map(np.column_stack([ground, true_h]))) - bias[2] - frame.to_geodetic(enu)[:, 2] + true_h
    # the DTM's own smooth error (0.1 m) and its smoothing of craters of 1.5 m and up
    error = heights - true_h
    assert np.sqrt(np.mean(error**2)) < 0.25
    assert np.sqrt(np.mean((unbiased - true_h) ** 2)) > 2 * np.sqrt(np.mean(error**2))  # the bias is there


def test_each_site_registers_within_half_a_metre_median_with_a_covariance_that_holds(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    orbital_map = traverse.measurements["orbital"][0]
    settings = mars_scenario.estimator.orbital
    bias = _true_bias(truth)
    rng = np.random.default_rng(3)
    errors, nees = [], []
    for stop in (s for s in traverse.stops if s.is_site):
        pose = gtsam.Pose3(truth.world_T_body[stop.index])
        guess = _map_pose(pose, bias)
        guess[:2, 3] += rng.normal(0.0, 2.0, 2)  # a predicted pose 2 m off
        points, covariances = site_point_cloud(stop, traverse.rig, traverse.image_noise_px)
        vertical = np.einsum("i,nij,j->n", pose.rotation().matrix()[2], covariances, pose.rotation().matrix()[2])
        result = register_site(points, vertical, guess, orbital_map.dtm, traverse.origin, 6.0,
                               DtmErrors(settings.surface_sigma_m, settings.dtm_sigma_m, settings.dtm_correlation_m),
                               settings.max_range_m, settings.min_points, settings.min_distinctness)
        error = result.measurement - predicted_measurement(pose, bias)
        errors.append(np.hypot(*error[:2]))
        nees.append(error @ np.linalg.solve(result.covariance, error))
    assert len(errors) >= 7
    assert np.median(errors) < 0.5
    # 4 dof per site, over 7-10 sites: a mean within [1, 8] (a covariance 40 % too small or too large fails)
    assert 1.0 < np.mean(nees) < 8.0, nees


def test_a_miscalibrated_pairs_sites_register_where_they_are_once_the_pixels_are_corrected(mars_scenario):
    """The right camera turned by about 0.025 deg: a disparity bias that stretches the far ground
    of every site's elevation map. Registered from the true pose, as measured the sites land 0.40
    m off (median) with a NEES of 9.5 for 4 dof; through the stereo_calibration kind's
    correction with the pair's error known, 0.16 m and 1.9."""
    scenario = mars_scenario.model_copy(update={"errors": SimulationErrors(boresight_sigma_deg=0.02)})
    traverse, truth = simulate(scenario, 1)
    error = np.array([truth.kinds["stereo_calibration"][name] for name in CALIBRATION_TERMS])
    assert abs(error[CALIBRATION_TERMS.index("right_rotation_y_rad")]) > 4e-4  # this draw
    kind = StereoCalibration.__new__(StereoCalibration)  # its correction, with the error as its estimate
    kind.loc = SimpleNamespace(traverse=traverse, smoother=SimpleNamespace(vector=lambda key: error))
    orbital_map, settings, bias = traverse.measurements["orbital"][0], scenario.estimator.orbital, _true_bias(truth)
    errors = DtmErrors(settings.surface_sigma_m, settings.dtm_sigma_m, settings.dtm_correlation_m)
    found = {}
    for label, corrected in (("as measured", None), ("corrected", kind.site_stereo_pixels)):
        off, nees = [], []
        for stop in (s for s in traverse.stops if s.is_site):
            pose = gtsam.Pose3(truth.world_T_body[stop.index])
            points, covariances = site_point_cloud(stop, traverse.rig, traverse.image_noise_px, corrected)
            vertical = np.einsum("i,nij,j->n", pose.rotation().matrix()[2], covariances, pose.rotation().matrix()[2])
            result = register_site(points, vertical, _map_pose(pose, bias), orbital_map.dtm, traverse.origin, 6.0,
                                   errors, settings.max_range_m, settings.min_points, settings.min_distinctness)
            miss = result.measurement - predicted_measurement(pose, bias)
            off.append(np.hypot(*miss[:2]))
            nees.append(miss @ np.linalg.solve(result.covariance, miss))
        found[label] = (np.median(off), np.mean(nees))
    assert found["as measured"][1] > 8.0  # the error is there: measured 9.5
    assert found["corrected"][0] < 0.25 and 1.0 < found["corrected"][1] < 8.0  # measured 0.16 m, 1.9


@pytest.fixture(scope="module")
def mars_run(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    return run(traverse, truth, mars_scenario.estimator, 7, RunOptions(configs=("vo_sites", ORBITAL)))


@pytest.mark.slow
def test_the_map_puts_the_traverse_in_place_and_its_bias_is_found_within_its_sigma(mars_run):
    orbital = mars_run.configurations[ORBITAL]
    counters = orbital.counters
    assert counters["orbital_registrations_used"] >= 6 and counters["orbital_uncovered_stops"] == []
    # the drawn bias (3 m, 1 m, 0.02 deg) against the estimate: within 3 sigma per component
    assert np.all(np.abs(counters["orbital_bias_error_sigmas"][0]) < 3.0), counters["orbital_bias_error_sigmas"]
    assert counters["orbital_registration_error_median_m"] < 0.5
    # without alignment (the map is an absolute reference) its error is that of VO + sites aligned
    assert orbital.metrics.ate_alignment == "none"
    assert orbital.metrics.ate_rmse_m < 0.5
    assert 0.2 < orbital.consistency.anees < 2.0


def _with_map(traverse, **changes):
    orbital_map = dataclasses.replace(traverse.measurements["orbital"][0], **changes)
    return dataclasses.replace(traverse, measurements={**traverse.measurements, "orbital": (orbital_map,)})


def _run_orbital(traverse, truth, scenario):
    return run(traverse, truth, scenario.estimator, 7, RunOptions(configs=(ORBITAL,))).configurations[ORBITAL]


@pytest.mark.slow
def test_a_map_that_leaves_out_part_of_the_traverse_names_the_uncovered_sites(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    dtm = traverse.measurements["orbital"][0].dtm
    keep = dtm.values.shape[0] // 2  # the south half: the start, not the second leg's far end
    top = dtm.y0_m - keep * dtm.post_m
    cropped = MapRaster(dtm.values[keep:].copy(), dtm.x0_m, top, dtm.post_m, dtm.crs_wkt)
    result = run(_with_map(traverse, dtm=cropped, orthoimage=None), truth, mars_scenario.estimator, 7,
                          RunOptions(configs=(ORBITAL,)))
    counters = result.configurations[ORBITAL].counters
    north = traverse.origin.to_map(truth.positions)[:, 1]
    sites = np.array([s.index for s in traverse.stops if s.is_site])
    uncovered = set(counters["orbital_uncovered_stops"])
    # a site's window reaches its points' range (40 m), the search (2-15 m) and two posts
    assert set(sites[north[sites] > top]) <= uncovered <= set(sites[north[sites] > top - 57.0])
    assert uncovered and counters["orbital_registrations_used"] >= 3
    # the run says so at its end, naming the stops
    from pancam_graph.api import _kind_warnings

    (warning,) = _kind_warnings(result)
    assert warning.startswith(f"{ORBITAL}: {len(uncovered)} site stops no orbital map covers")
    assert str(min(uncovered)) in warning


def test_a_map_that_misses_the_start_is_refused_by_name(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    dtm = traverse.measurements["orbital"][0].dtm
    elsewhere = MapRaster(dtm.values, dtm.x0_m + 5000.0, dtm.y0_m, dtm.post_m, dtm.crs_wkt)
    with pytest.raises(InputError, match="'orbital_map' does not cover the traverse's start"):
        _run_orbital(_with_map(traverse, dtm=elsewhere, orthoimage=None), truth, mars_scenario)


def test_a_map_of_earth_under_a_mars_traverse_is_refused(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    dtm = traverse.measurements["orbital"][0].dtm
    utm = CRS.from_epsg(32644).to_wkt()
    with pytest.raises(InputError, match="body of radius 6,378,137 m, the traverse is on mars"):
        _run_orbital(_with_map(traverse, dtm=dataclasses.replace(dtm, crs_wkt=utm), orthoimage=None), truth,
                     mars_scenario)


def test_an_orthoimage_that_disagrees_with_its_dtm_is_refused(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    ortho = traverse.measurements["orbital"][0].orthoimage
    away = dataclasses.replace(ortho, x0_m=ortho.x0_m + 10_000.0)
    with pytest.raises(InputError, match="orthoimage and DTM do not overlap"):
        _run_orbital(_with_map(traverse, orthoimage=away), truth, mars_scenario)
    other_crs = dataclasses.replace(ortho, crs_wkt=CRS.from_wkt(ortho.crs_wkt).to_wkt().replace(
        "18.4447", "18.5"))
    with pytest.raises(InputError, match="orthoimage and DTM are in different CRSs"):
        _run_orbital(_with_map(traverse, orthoimage=other_crs), truth, mars_scenario)


@pytest.mark.slow
def test_a_hole_in_the_dtm_under_a_site_skips_that_site_and_says_so(mars_traverse, mars_scenario):
    traverse, truth = mars_traverse
    dtm = traverse.measurements["orbital"][0].dtm
    site = [s.index for s in traverse.stops if s.is_site][3]
    col, row = ((traverse.origin.to_map(truth.positions[[site]])[0] - [dtm.x0_m, dtm.y0_m]) / dtm.post_m * [1, -1])
    holed = dtm.values.copy()
    holed[int(row) - 20:int(row) + 20, int(col) - 20:int(col) + 20] = np.nan
    counters = _run_orbital(_with_map(traverse, dtm=dataclasses.replace(dtm, values=holed)), truth,
                            mars_scenario).counters
    failed = counters["orbital_failed_stops"]
    assert any(f.startswith(f"stop {site},") and "no data" in f for f in failed), failed
    assert counters["orbital_registrations_used"] >= 5


def test_a_map_file_in_degrees_is_refused_naming_the_file(mars_traverse, mars_scenario, tmp_path):
    traverse, truth = mars_traverse
    write_observations(tmp_path, traverse, mars_scenario.estimator, 7, truth)
    dtm = read_map_raster(tmp_path / "maps" / "orbital_map_dtm.tif")
    geographic = CRS.from_wkt(dtm.crs_wkt).geodetic_crs.to_wkt()
    write_map_raster(tmp_path / "maps" / "orbital_map_dtm.tif", dataclasses.replace(dtm, crs_wkt=geographic))
    with pytest.raises(InputError, match=r"orbital_map_dtm.tif: CRS .* is geographic"):
        read_observations(tmp_path)


def test_registration_refuses_a_site_it_cannot_place(mars_traverse):
    traverse, truth = mars_traverse
    dtm = traverse.measurements["orbital"][0].dtm
    flat = dataclasses.replace(dtm, values=np.full_like(dtm.values, np.nanmean(dtm.values)))
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-20, 20, (200, 2)), rng.normal(-1.5, 0.05, 200)])
    pose = _map_pose(gtsam.Pose3(truth.world_T_body[0]), np.zeros(4))
    with pytest.raises(RegistrationFailed, match="ambiguous"):
        register_site(points, np.full(200, 0.01), pose, flat, traverse.origin, 4.0)
    with pytest.raises(RegistrationFailed, match="fewer than 30"):
        register_site(points[:10], np.full(10, 0.01), pose, dtm, traverse.origin, 4.0)


@pytest.mark.slow
def test_rerun_shows_the_orthoimage_on_the_dtm_and_as_the_2d_map(mars_traverse, mars_scenario, tmp_path):
    from rrd import Recording, array

    from pancam_graph.viz.rerun_live import RerunRecorder
    from pancam_graph.viz.rerun_scene import MESH_DROP_M, MESH_POSTS
    from pancam_graph.viz.rerun_sink import RerunTarget, open_recording

    traverse, truth = mars_traverse
    recording = open_recording(RerunTarget("save", path=tmp_path / "run.rrd"), "test")
    run(traverse, truth, mars_scenario.estimator, 1, RunOptions(configs=("vo_sites_orbital",)),
                 listener=RerunRecorder(recording))
    recording.close()
    rec = Recording(tmp_path / "run.rrd")
    assert {"/world/orbital_map", "/orbital_map/image", "/orbital_map/truth",
            "/orbital_map/vo_sites_orbital"} <= rec.entity_paths
    vertices = array(rec.latest("/world/orbital_map", "Mesh3D:vertex_positions"))
    texcoords = array(rec.latest("/world/orbital_map", "Mesh3D:vertex_texcoords"))
    assert len(vertices) <= MESH_POSTS**2 and len(texcoords) == len(vertices)
    assert texcoords.min() > -0.01 and texcoords.max() < 1.01  # the orthoimage covers the DTM
    # the ground under the truth's path (the map's own georeference: its bias apart, metres), drawn
    # low by the drop and twice the map's stated vertical error, and so below the trajectory
    near = np.linalg.norm(vertices[:, None, :2] - truth.positions[None, ::50, :2], axis=2).argmin(axis=0)
    drop = MESH_DROP_M + 2.0 * traverse.measurements["orbital"][0].vertical_sigma_m
    assert np.all(np.abs(vertices[near, 2] + drop - truth.positions[::50, 2]) < 3.0)
    assert np.median(vertices[near, 2] - truth.positions[::50, 2]) < -1.0
    image = array(rec.latest("/orbital_map/image", "Image:buffer"))
    assert image.size > 10_000
    path = array(rec.latest("/orbital_map/vo_sites_orbital", "LineStrips2D:strips")[0])
    assert len(path) == len(traverse.stops) and path.min() >= 0


@pytest.mark.slow
def test_neighbouring_registrations_share_an_error_so_the_bias_averages_less(mars_traverse, mars_scenario, mars_run):
    """With neighbour_correlation 0.25 (a moving average of order one), N registrations in a row
    tell the map bias what N / 1.5 independent ones would: its sigma east and north grows by
    up to sqrt(1.5) = 1.22 against independent registrations (less, as the VO and the prior
    also bound it), the rotation's hardly (the prior holds it). Every registration but the
    first of a chain shares its predecessor's error."""
    traverse, truth = mars_traverse
    settings = mars_scenario.estimator.orbital
    assert settings.neighbour_correlation == 0.25
    independent_estimator = mars_scenario.estimator.model_copy(
        update={"orbital": settings.model_copy(update={"neighbour_correlation": 0.0})})
    independent = run(traverse, truth, independent_estimator, 7, RunOptions(configs=(ORBITAL,)))
    shared = mars_run.configurations[ORBITAL].counters
    alone = independent.configurations[ORBITAL].counters
    assert shared["orbital_registrations_used"] == alone["orbital_registrations_used"] >= 6
    ratio = np.array(shared["orbital_bias_sigma"][0]) / np.array(alone["orbital_bias_sigma"][0])
    assert np.all(1.05 < ratio[:2]) and np.all(ratio[:2] < 1.23), ratio
    assert 0.99 < ratio[3] < 1.05, ratio


@pytest.mark.slow
def test_a_sites_ground_from_above_is_found_in_the_orthoimage_and_used(mars_traverse, mars_scenario):
    """Each site given the ground the map's orthoimage shows around it (as an image folder's
    dense stereo would give it, here made from the orthoimage with grey-level noise): the kind
    correlates it, adds an east-north factor per site, and its errors against the truth hold."""
    from pancam_graph.records import GroundPatch

    traverse, truth = mars_traverse
    ortho = traverse.measurements["orbital"][0].orthoimage  # 1 m pixels in this fixture
    bias = _true_bias(truth)
    frame = traverse.origin
    rng = np.random.default_rng(5)
    g = np.arange(-30.0, 30.0, 0.5)
    stops = list(traverse.stops)
    for stop in (s for s in stops if s.is_site):
        world_T_body = truth.world_T_body[stop.index]
        xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2) + world_T_body[:2, 3]
        world = np.column_stack([xy, truth.terrain(xy)])
        grey = ortho.at(frame.to_map(np.column_stack([MapBias(bias[0], bias[1], bias[3]).to_map(xy), world[:, 2]])))
        body = (world - world_T_body[:3, 3]) @ world_T_body[:3, :3]
        seen = np.isfinite(grey)
        stops[stop.index] = dataclasses.replace(stop, ground=GroundPatch(
            body[seen].astype(np.float32), (grey[seen] + rng.normal(0.0, 3.0, seen.sum())).astype(np.float32),
            np.full(seen.sum(), 8, np.int32), 0.5))
    with_ground = dataclasses.replace(traverse, stops=tuple(stops))
    counters = _run_orbital(with_ground, truth, mars_scenario).counters
    sites = sum(s.is_site for s in traverse.stops)
    assert counters["orbital_ortho_registrations_used"] >= sites - 1, counters["orbital_failed_stops"]
    assert counters["orbital_ortho_error_median_m"] < 0.3  # measured: 0.10 m (1 m pixels)
    assert 0.2 < counters["orbital_ortho_nees_mean"] < 3.0  # 2 dof; measured 0.70 (the 0.2 m floor)
    assert np.all(np.abs(counters["orbital_bias_error_sigmas"][0]) < 3.0)
