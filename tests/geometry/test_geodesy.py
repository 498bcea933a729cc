import numpy as np
import pytest
from pyproj import CRS

from pancam_graph.errors import GeodesyError
from pancam_graph.geometry.geodesy import LocalFrame

A = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)


def _ecef(lat_deg, lon_deg, h):
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = A / np.sqrt(1.0 - E2 * np.sin(lat) ** 2)
    return np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - E2) + h) * np.sin(lat)])


def _enu_by_hand(lat0, lon0, h0, lat, lon, h):
    """Independent computation: ECEF difference rotated into the local tangent frame."""
    d = _ecef(lat, lon, h) - _ecef(lat0, lon0, h0)
    la, lo = np.radians(lat0), np.radians(lon0)
    rot = np.array([
        [-np.sin(lo), np.cos(lo), 0.0],
        [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
        [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
    ])
    return rot @ d


def test_enu_matches_independent_ecef_computation():
    frame = LocalFrame(39.7392, -105.1450, 1705.0)
    point = (39.7410, -105.1501, 1721.5)
    expected = _enu_by_hand(39.7392, -105.1450, 1705.0, *point)
    np.testing.assert_allclose(frame.to_enu(*point)[0], expected, atol=1e-4)
    assert expected[0] < 0 and expected[1] > 0  # west and north of the origin


def test_round_trip_below_a_millimetre():
    frame = LocalFrame(39.7392, -105.1450, 1705.0)
    rng = np.random.default_rng(1)
    enu = rng.uniform([-20000, -20000, -200], [20000, 20000, 800], size=(500, 3))
    back = frame.to_enu(*frame.to_geodetic(enu).T)
    assert np.abs(back - enu).max() < 1e-3


def test_bad_input_raises_typed_errors():
    frame = LocalFrame(0.0, 0.0, 0.0)
    with pytest.raises(GeodesyError, match="non-finite"):
        frame.to_enu(np.nan, 0.0, 0.0)
    with pytest.raises(GeodesyError, match="latitude"):
        frame.to_enu(91.0, 0.0, 0.0)
    with pytest.raises(GeodesyError):
        LocalFrame(95.0, 0.0, 0.0)


def test_numpy_scalar_origin_is_the_same_frame():
    lat, lon, h = np.array([49.015003823272, 8.4342971002335, 116.43032836914])
    frame = LocalFrame(lat, lon, h)  # numpy scalars, as they come out of a loaded table
    np.testing.assert_allclose(frame.to_enu(lat, lon, h), [[0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(frame.to_enu(lat + 1e-3, lon, h), LocalFrame(float(lat), float(lon), float(h))
                               .to_enu(lat + 1e-3, lon, h), atol=1e-9)


def test_a_mars_frame_has_its_positions_on_the_iau_sphere_and_its_up_along_the_ellipsoid_normal():
    """One degree north of the origin on the sphere (R = 3,396,190 m): the chord between the two
    points, rotated into east-north-up whose up is the IAU 2015 ellipsoid's normal (planetographic
    latitude tan(lat_g) = (a / b)^2 tan(lat_c), closed form on the surface)."""
    from pancam_graph.geometry.geodesy import MARS_RADIUS_M

    frame = LocalFrame(-4.59, 137.44, 0.0, body="mars")  # Gale crater

    def on_sphere(lat, lon):
        la, lo = np.radians(lat), np.radians(lon)
        return MARS_RADIUS_M * np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])

    # the origin's planetographic latitude: of the ellipsoid's normal through it (Bowring's iteration)
    x, _, z = on_sphere(-4.59, 0.0)
    e2, lat_g = 1.0 - (3376200.0 / 3396190.0) ** 2, np.arctan2(z, x)
    for _ in range(10):
        n = 3396190.0 / np.sqrt(1.0 - e2 * np.sin(lat_g) ** 2)
        lat_g = np.arctan2(z, x * (1.0 - e2 * n / (n + x / np.cos(lat_g) - n)))
    lat_g = np.degrees(lat_g)
    assert frame.up_lat_deg == pytest.approx(lat_g, abs=1e-9) and lat_g - -4.59 == pytest.approx(-0.0543, abs=1e-4)

    la, lo = np.radians(lat_g), np.radians(137.44)
    enu_R_fixed = np.array([[-np.sin(lo), np.cos(lo), 0.0],
                            [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                            [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    expected = enu_R_fixed @ (on_sphere(-3.59, 137.44) - on_sphere(-4.59, 137.44))
    enu = frame.to_enu(-3.59, 137.44, 0.0)[0]
    np.testing.assert_allclose(enu, expected, atol=1e-3)
    np.testing.assert_allclose(frame.enu_R_fixed(), enu_R_fixed, atol=1e-12)
    np.testing.assert_allclose(frame.to_geodetic(enu[None])[0], [-3.59, 137.44, 0.0], atol=1e-9)
    # the same degree on Earth's ellipsoid is 111 km, not Mars' 59 km
    assert LocalFrame(-4.59, 137.44, 0.0).to_enu(-3.59, 137.44, 0.0)[0, 1] > 110_000.0


def test_on_earth_up_is_wgs84_s_normal_and_turns_with_distance():
    """On Earth the frame's up is the geodetic vertical (WGS84's normal): up_at 10 km east turns
    by 10 km over the prime vertical's radius (the independent ECEF computation above)."""
    frame = LocalFrame(39.7392, -105.1450, 1705.0)
    assert frame.up_lat_deg == 39.7392
    east = frame.to_geodetic(np.array([[10_000.0, 0.0, 0.0]]))[0]
    up_there = _ecef(east[0], east[1], east[2] + 1.0) - _ecef(*east)
    expected = _enu_by_hand(39.7392, -105.1450, 1705.0, *east[:2], east[2] + 1.0) - \
        _enu_by_hand(39.7392, -105.1450, 1705.0, *east)
    assert np.linalg.norm(up_there) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(frame.up_at(np.array([[10_000.0, 0.0, 0.0]]))[0], expected, atol=1e-9)
    assert np.degrees(np.arccos(expected[2])) == pytest.approx(np.degrees(10_000.0 / 6_387_000.0), rel=3e-3)


def test_a_site_map_is_in_the_body_s_map_projection():
    from pancam_graph.geometry.geodesy import MARS_RADIUS_M

    mars = LocalFrame(-4.59, 137.44, 0.0, body="mars")
    crs = mars.map_crs()
    assert crs.is_projected and "Mars" in crs.name and "Equirectangular" in crs.name
    assert crs.geodetic_crs == CRS.from_user_input("IAU_2015:49900")  # the IAU 2015 sphere
    # equirectangular on the sphere, centre longitude 0, true scale at the site's latitude:
    # x = R cos(lat0) lon, y = R lat (radians)
    np.testing.assert_allclose(mars.to_map(np.zeros((1, 3)))[0],
                               MARS_RADIUS_M * np.deg2rad([137.44 * np.cos(np.deg2rad(-4.59)), -4.59]), atol=1e-3)
    steps = np.diff(mars.to_map(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [100.0, 100.0, 0.0]])), axis=0)
    np.testing.assert_allclose(steps, [[100.0, 0.0], [0.0, 100.0]], atol=2e-3)  # square on the ground
    enu = np.array([[120.0, -80.0, 0.0], [-3.0, 40.0, 0.0]])
    # a map point is ENU only with its height: up is the ellipsoid's normal, not the sphere's
    np.testing.assert_allclose(mars.from_map(mars.to_map(enu), mars.to_geodetic(enu)[:, 2]), enu, atol=1e-6)
    earth = LocalFrame(49.0, 8.4, 110.0)
    assert earth.map_crs().to_epsg() == 32632  # UTM 32 N
    steps = np.diff(earth.to_map(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]])), axis=0)[0]
    assert np.hypot(*steps) == pytest.approx(100.0 * 0.99962, rel=2e-4)  # UTM's scale near its meridian


def test_an_unknown_body_is_named():
    with pytest.raises(GeodesyError, match="body 'moon': expected earth or mars"):
        LocalFrame(0.0, 0.0, 0.0, body="moon")


def test_a_results_folder_keeps_its_frame_s_body(tmp_path):
    import json

    from pancam_graph.errors import ResultsError
    from pancam_graph.store.results_folder import LOCAL_FRAME_FILE, local_frame_dict, read_local_frame

    mars = LocalFrame(-4.59, 137.44, -4500.0, body="mars")
    (tmp_path / LOCAL_FRAME_FILE).write_text(json.dumps(local_frame_dict(mars)))
    assert read_local_frame(tmp_path) == mars
    earth = LocalFrame(49.0, 8.4, 110.0)
    (tmp_path / LOCAL_FRAME_FILE).write_text(json.dumps(local_frame_dict(earth)))
    assert read_local_frame(tmp_path) == earth and "body" not in local_frame_dict(earth)  # as before
    (tmp_path / LOCAL_FRAME_FILE).write_text(json.dumps({**local_frame_dict(mars), "body": "venus"}))
    with pytest.raises(ResultsError, match=r"local_frame.json: expected .*body 'venus': expected earth or mars"):
        read_local_frame(tmp_path)


def test_a_scenario_on_mars_keeps_its_body_through_the_observation_folder(tmp_path):
    from pancam_graph import api
    from pancam_graph.config import bundled_scenarios
    from pancam_graph.errors import ConfigError
    from pancam_graph.store.observation_folder import read_observations
    from pancam_graph.store.results_folder import read_local_frame

    text = bundled_scenarios()["short_trail"].read_text()
    mars = tmp_path / "mars.toml"
    mars.write_text(text.replace("[origin]\n", '[origin]\nbody = "mars"\n', 1))
    with pytest.raises(ConfigError, match="there is no GPS on Mars"):
        api.simulate(mars, tmp_path / "refused")
    mars.write_text(mars.read_text() + "\n[gps]\nenabled = false\n\n[sun_heading]\nenabled = false\n")
    traverse = api.simulate(mars, tmp_path / "observations")
    assert traverse.origin.body == "mars" and not traverse.gps_fixes
    back = read_observations(tmp_path / "observations").traverse
    assert back.origin == traverse.origin
    # a run's exports: no WGS84 formats for a Mars trajectory, its own geodetic CSV instead
    api.run(tmp_path / "observations", out=tmp_path / "run", configs=("vo",), figures=False, processes=1)
    names = {p.name for p in (tmp_path / "run").iterdir()}
    assert "trajectory_vo_mars_iau2015.csv" in names and "trajectory_vo.tum" in names
    assert not names & {"trajectory_vo_wgs84.csv", "trajectory_vo.geojson", "trajectory_vo.kml"}
    assert read_local_frame(tmp_path / "run") == traverse.origin
    # the same east-north-up offsets are other geodetic points on a sphere of Mars' size
    assert not np.allclose(back.origin.to_geodetic(np.array([[1000.0, 0.0, 0.0]])),
                           LocalFrame(back.origin.lat0_deg, back.origin.lon0_deg, back.origin.h0_m).to_geodetic(
                               np.array([[1000.0, 0.0, 0.0]])))
