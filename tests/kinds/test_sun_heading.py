"""The sun-sensor heading kind: its ephemerides against published values, its simulation
leaving every other simulated number alone, its observation-folder table read back bit for bit
(bad rows named), and the heading it gives a dead-reckoning traverse against the truth."""

import datetime as dt

import numpy as np
import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError, InputError
from pancam_graph.geometry.geodesy import LocalFrame
from pancam_graph.kinds.sun_heading import SunSensor, start_utc_s, sun_directions_enu
from pancam_graph.sim import simulate
from pancam_graph.solve.pipeline import RunOptions, run_scenario
from pancam_graph.store.observation_folder import read_observations
from pancam_graph.store.observation_writer import write_observations

DENVER = LocalFrame(39.7392, -105.1450, 1705.0)
WITH_SUN = "dead_reckoning+wheel_slip+sun_heading"


def _elevation_deg(directions: np.ndarray) -> np.ndarray:
    return np.rad2deg(np.arcsin(directions[:, 2]))


def test_the_suns_highest_at_denver_on_the_june_solstice_is_90_minus_latitude_plus_obliquity():
    day = dt.datetime(2026, 6, 21, tzinfo=dt.UTC).timestamp()
    sun = sun_directions_enu("earth", DENVER, day + np.arange(0, 86400, 30.0))
    noon = np.argmax(sun[:, 2])
    assert _elevation_deg(sun)[noon] == pytest.approx(90.0 - 39.7392 + 23.436, abs=0.05)
    assert abs(sun[noon, 0]) < 0.01 and sun[noon, 1] < 0  # due south of a northern site at noon
    # local solar noon near 12:00 - 105.145 / 15 h UTC (the equation of time is -1.7 min then)
    assert (noon * 30.0) / 3600 == pytest.approx(12.0 + 105.145 / 15.0, abs=0.1)


def test_mars24_against_its_published_worked_example_and_the_subsolar_point():
    """Allison & McEwen (2000), Mars24's worked example A: 2000-01-06 00:00 UTC (TT - UTC = 64.184 s
    then), Ls = 277.18758 deg. The sun's direction from Mars' centre has the declination
    asin(0.42565 sin Ls) = -24.981 deg: the sun is overhead where the ellipsoid's normal points
    that way (planetographic latitude -24.981). Mars24's "planetographic declination", -25.2282
    deg, is the planetographic latitude of the surface point under the line from Mars' centre to
    the sun (planetocentric -24.981): there the sun stands 0.26 deg from the zenith."""
    import marstime

    j2000 = marstime.j2000_offset_tt(marstime.julian_tt(2451549.5))
    ls = marstime.Mars_Ls(j2000)
    assert ls == pytest.approx(277.18758, abs=1e-3)  # marstime 0.5.6: 277.18677
    utc = dt.datetime(2000, 1, 6, tzinfo=dt.UTC).timestamp()
    subsolar_east = -marstime.subsolar_longitude(j2000) % 360.0
    declination = np.degrees(np.arcsin(0.42565 * np.sin(np.radians(ls))))
    assert declination == pytest.approx(-24.981, abs=1e-3)
    normal_at_sun = np.degrees(np.arctan(np.tan(np.radians(declination)) * (3376200.0 / 3396190.0) ** 2))
    overhead = sun_directions_enu("mars", LocalFrame(normal_at_sun, subsolar_east, 0.0, body="mars"), [utc])
    assert _elevation_deg(overhead)[0] > 89.999
    under_the_sun = sun_directions_enu("mars", LocalFrame(declination, subsolar_east, 0.0, body="mars"), [utc])
    assert _elevation_deg(under_the_sun)[0] == pytest.approx(90.0 - abs(-25.2282 - declination), abs=0.02)


def test_the_default_start_is_nine_in_the_morning_local_mean_solar_time():
    start = dt.datetime.fromtimestamp(start_utc_s(SunSensor(), DENVER), dt.UTC)
    assert start.date() == dt.date(2026, 6, 21)
    assert start.hour + start.minute / 60 == pytest.approx(9.0 + 105.145 / 15.0, abs=1 / 60)


def test_sightings_change_no_other_simulated_number(short_scenario):
    without = short_scenario.model_copy(update={"sun_heading": SunSensor(enabled=False)})
    a, truth_a = simulate(short_scenario, 4)
    b, truth_b = simulate(without, 4)
    assert a.measurements["sun_heading"] and "sun_heading" not in b.measurements
    assert np.array_equal(truth_a.world_T_body, truth_b.world_T_body)
    assert np.array_equal(a.start_world_T_body, b.start_world_T_body) and a.gps_fixes == b.gps_fixes
    for sa, sb in zip(a.stops, b.stops, strict=True):
        assert np.array_equal(sa.stereo.uvv, sb.stereo.uvv)
        assert [f.observations.uvv.tolist() for f in sa.panorama] == [f.observations.uvv.tolist() for f in sb.panorama]


def test_sightings_are_at_sites_with_the_sun_up_and_as_accurate_as_stated(short_scenario):
    traverse, truth = simulate(short_scenario.model_copy(update={"sun_heading": SunSensor(sigma_deg=0.5)}), 0)
    sightings = traverse.measurements["sun_heading"]
    assert {s.stop for s in sightings} <= {s.index for s in traverse.stops if s.is_site}
    reference = sun_directions_enu("earth", traverse.origin, [s.utc_s for s in sightings])
    true_body = np.array([truth.world_T_body[s.stop][:3, :3].T @ n for s, n in zip(sightings, reference, strict=True)])
    angle = np.rad2deg(np.arccos(np.clip(np.sum(true_body * [s.sun_body for s in sightings], axis=1), -1, 1)))
    assert np.all(_elevation_deg(reference) >= 10.0)
    # the angle of two 0.5 deg normal axes is Rayleigh: below 3.5 sigma with probability 0.998
    assert np.all(angle < 3.5 * 0.5) and np.mean(angle) > 0.1


def test_the_table_reads_back_bit_for_bit_and_bad_rows_are_named(short_scenario, tmp_path):
    traverse, truth = simulate(short_scenario, 2)
    write_observations(tmp_path, traverse, short_scenario.estimator, 2, truth)
    again = read_observations(tmp_path).traverse.measurements["sun_heading"]
    for a, b in zip(traverse.measurements["sun_heading"], again, strict=True):
        assert (a.stop, a.utc_s) == (b.stop, b.utc_s)
        assert np.array_equal(a.sun_body, b.sun_body) and np.array_equal(a.up_body, b.up_body)
    table = tmp_path / "sun_heading.csv"
    lines = table.read_text().splitlines()
    original = list(lines)
    lines[2] = ",".join(lines[2].split(",")[:2] + ["0.1", "0.1", "0.1"] + lines[2].split(",")[5:])
    table.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"sun_heading.csv: line 3: sun_x, sun_y, sun_z must be a unit vector"):
        read_observations(tmp_path)
    lines[2] = "9999," + ",".join(lines[1].split(",")[1:])
    table.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"sun_heading.csv: line 3: stop 9999 is not one of"):
        read_observations(tmp_path)
    lines[2] = lines[1]  # a repeated row was dropped without a word
    table.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"sun_heading.csv: line 3: stop \d+ has a sighting already \(line 2\)"):
        read_observations(tmp_path)
    for utc_s in ("1e20", "-1e11"):  # beyond the ephemerides' years (pandas refused them deep inside)
        lines[2] = ",".join(original[2].split(",")[:1] + [utc_s] + original[2].split(",")[2:])
        table.write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError, match=r"sun_heading.csv: line 3: utc_s .* outside the years 1960-2199"):
            read_observations(tmp_path)


@pytest.mark.parametrize("section, words", [
    ("[sun_heading]\nsigma_deg = -1.0", r"field 'sun_heading.sigma_deg': Input should be greater than or equal to 0"),
    ('[sun_heading]\nplanet = "mars"', r"planet 'mars' needs start_utc"),
    ('[estimator.sun_heading]\nplanet = "venus"', r"field 'estimator.sun_heading.planet'"),
    ("[sun_heading]\ndate = 0001-01-01", r"date 0001-01-01: the sun's ephemerides are used for years 1960-2199"),
    ("[sun_heading]\ndate = 9999-12-31", r"date 9999-12-31: the sun's ephemerides are used for years 1960-2199"),
    ("[sun_heading]\nstart_utc = 2300-01-01T00:00:00Z", r"start_utc 2300-01-01 00:00:00\+00:00: the sun's"),
])
def test_a_bad_section_is_named(tmp_path, section, words):
    (tmp_path / "s.toml").write_text(resolve_scenario("short_trail").read_text() + "\n" + section + "\n")
    with pytest.raises(ConfigError, match=words):
        load_scenario(tmp_path / "s.toml")


@pytest.fixture(scope="module")
def denver_dead_reckoning():
    scenario = load_scenario(resolve_scenario("denver_trail"))
    return run_scenario(scenario, RunOptions(seed=1, configs=("dead_reckoning", WITH_SUN)))


def _heading_deg(world_T_body):
    return np.rad2deg(np.arctan2(world_T_body[..., 1, 0], world_T_body[..., 0, 0]))


@pytest.mark.slow
def test_sun_sightings_hold_dead_reckonings_heading_within_the_sensors_three_sigma(denver_dead_reckoning):
    result = denver_dead_reckoning
    sightings = result.traverse.measurements["sun_heading"]
    stops = np.array([s.stop for s in sightings])
    truth = result.truth.world_T_body
    reference = sun_directions_enu("earth", result.traverse.origin, [s.utc_s for s in sightings])
    bound = 3 * 0.3 / np.cos(np.arcsin(reference[:, 2]))  # the sensor's 3 sigma in heading, degrees
    errors = {}
    for name, config in result.configurations.items():
        errors[name] = np.abs((_heading_deg(config.world_T_body[stops]) - _heading_deg(truth[stops]) + 180) % 360 - 180)
    assert np.all(errors[WITH_SUN] <= bound), errors[WITH_SUN] / bound
    assert np.max(errors["dead_reckoning"]) > 3 * np.max(errors[WITH_SUN])  # the gyro drift it removes
    counters = result.configurations[WITH_SUN].counters
    assert counters["sun_sightings_used"] == len(sightings) >= 15
    assert counters["sun_sightings_flagged"] == 0


def test_with_the_sun_dead_reckoning_stays_consistent(denver_dead_reckoning):
    consistency = denver_dead_reckoning.configurations[WITH_SUN].consistency
    # one run's stops are not independent samples (the band of metrics.json treats them so):
    # the Monte Carlo over seeds is docs/sun_heading.md's; here, within half of 1 either way
    assert 0.67 < consistency.anees < 1.5


@pytest.mark.parametrize("change, words", [
    (("start_utc = 2026-06-15T06:00:00Z", ""), r"\[sun_heading\] on mars needs start_utc"),
    (("[sun_heading]", '[estimator.sun_heading]\nplanet = "earth"\n\n[sun_heading]'),
     r"\[estimator.sun_heading\] planet = 'earth' but the origin is on mars"),
])
def test_on_mars_the_sun_is_mars_and_needs_a_start_time(tmp_path, change, words):
    text = resolve_scenario("mars_traverse").read_text()
    assert change[0] in text
    (tmp_path / "s.toml").write_text(text.replace(*change))
    with pytest.raises(ConfigError, match=words):
        load_scenario(tmp_path / "s.toml")
