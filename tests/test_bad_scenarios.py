"""Scenario and manifest fields are finite and physical, cross-field checks hold, and the TOML
reader takes what editors write (a byte-order mark, CRLF) and names a file that is not UTF-8
(issue 15). Each case is an input that once crashed mid-run, allocated without bound or ran
nonsense."""

import math
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import tomli_w

from pancam_graph.config import bundled_scenarios, load_scenario
from pancam_graph.errors import ConfigError

SHORT = bundled_scenarios()["short_trail"]


def _scenario(tmp_path: Path, change) -> Path:
    data = tomllib.loads(SHORT.read_text())
    change(data)
    path = tmp_path / "bad.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def change(data):
        node = data
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        node[keys[-1]] = value
    return change


def _waypoint(value):
    def change(data):
        data["path"]["waypoints"][1][0] = value
    return change


def _path(waypoints):
    def change(data):
        data["path"]["waypoints"] = waypoints
        data["path"]["sharp_turns"] = []
    return change


@pytest.mark.parametrize("change,words", [
    (_set("origin", "h_m", math.nan), ["origin.h_m", "finite"]),
    (_set("estimator", "vo_error_model", [1.0]), ["estimator.vo_error_model", "pixel_noise", "real_images"]),
    (_set("estimator", "vo_error_model", {"a": 1}), ["estimator.vo_error_model", "pixel_noise"]),
    (_set("estimator", "vo_sigma_scale", [1.0, 1.0, 0.0, 1.8, 1.65, 1.0]),
     ["estimator.vo_sigma_scale.2", "greater than 0"]),  # a singular VO covariance, the field unnamed
    (_set("estimator", "vo_sigma_scale", [1.0, 1.8]), ["estimator.vo_sigma_scale.2", "Field required"]),
    (_waypoint(math.inf), ["path.waypoints.1.0", "finite"]),
    (_waypoint(1e308), ["path.waypoints.1.0", "less than or equal to 1000000"]),
    (_set("path", "speed_mps", 1e308), ["path.speed_mps", "less than or equal to 10"]),
    (_set("path", "stop_spacing_m", [0.0, 1.0]), ["stop_spacing_m", "0.05 <= min <= max"]),
    (_set("camera", "vo_range_m", [25.0, 2.0]), ["camera.vo_range_m", "min <= max"]),
    (_set("camera", "image_noise_px", math.inf), ["camera.image_noise_px", "finite"]),
    (_set("sites", "pan_step_deg", 1e-9), ["sites.pan_step_deg", "greater than or equal to 1"]),
    (_set("sites", "tilts_deg", [-6.0, 1e308]), ["sites.tilts_deg.1", "less than or equal to 90"]),
    (_set("sites", "pan_step_deg", 1.0), None),  # 361 x 2 tilts: fine
    (lambda d: (_set("sites", "pan_step_deg", 1.0)(d), _set("sites", "tilts_deg", [-19.0 + t for t in range(20)])(d)),
     ["7581 frames per site"]),  # 361 pans x 20 tilts + 361 HRC frames
    (_set("terrain", "featureless", [[300.0, 100.0]]), ["terrain.featureless.0", "min <= max"]),
    (_set("gps", "lever_arm_m", [0.0, 0.0, 1e308]), ["lever_arm_m", "within 10 m"]),
    (_set("dead_reckoning", "wheel_slip_mean", math.nan), ["dead_reckoning.wheel_slip_mean", "finite"]),
    (_set("estimator", "start_sigma_m", math.inf), ["estimator.start_sigma_m", "finite"]),
    (_path([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), ["waypoints 0 and 1 are the same point"]),
    (_path([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]), ["the path is 0.50 m long"]),
    (_set("name", "trail\x00x"), ["name", "should match pattern"]),
    (_set("name", "../elsewhere"), ["name", "should match pattern"]),
    (_set("seed", 2**64), ["seed", "less than 9223372036854775808"]),
    (_set("sites", "tilts_deg", []), ["field 'sites': tilts_deg is empty: a site panorama needs at least one tilt"]),
    (_set("gps", "every_n_stops", 10**9), ["gps.every_n_stops", "less than or equal to 1000"]),
    (lambda d: (_set("camera", "vo_range_m", [25.0, 2.0])(d), _set("bogus", 1)(d)),
     ["2 problems: field 'camera.vo_range_m': must be (min, max) with min <= max (got [25.0, 2.0]); "
      "field 'bogus': unknown key"]),
])
def test_a_bad_field_is_named(tmp_path, change, words):
    path = _scenario(tmp_path, change)
    if words is None:
        load_scenario(path)
        return
    with pytest.raises(ConfigError) as error:
        load_scenario(path)
    message = str(error.value)
    assert str(path) in message and "\n" not in message  # one line, however many problems
    for word in words:
        assert word in message, (word, message)


def test_a_byte_order_mark_and_crlf_are_read_and_other_bytes_named(tmp_path):
    text = SHORT.read_text()
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert load_scenario(bom) == load_scenario(SHORT)
    latin = tmp_path / "latin1.toml"
    latin.write_bytes(text.replace('description = "', 'description = "caf\xe9 ').encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1.toml: not UTF-8 text \(byte \d+"):
        load_scenario(latin)


@pytest.mark.slow
def test_the_cli_says_which_field_and_writes_nothing(tmp_path):
    path = _scenario(tmp_path, _set("camera", "vo_range_m", [25.0, 2.0]))
    exe = Path(sys.executable).parent / "pancam-graph"
    result = subprocess.run([str(exe), "run", str(path), "--out", str(tmp_path / "out")], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "camera.vo_range_m" in result.stderr and "min <= max" in result.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_an_orbital_map_near_a_pole_is_refused_before_the_run(tmp_path):
    """mars_excerpt moved to the south pole: the simulated map's equirectangular projection has no
    width there (it raised numpy's 'negative dimensions' deep in the map's sampling)."""
    text = bundled_scenarios()["mars_excerpt"].read_text().replace("lat_deg = 18.4447", "lat_deg = -90.0", 1)
    assert "lat_deg = -90.0" in text
    path = tmp_path / "polar.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"\[orbital\] at latitude -90: a simulated orbital map is equirectangular"):
        load_scenario(path)


def test_a_traverse_far_beyond_what_a_run_takes_is_refused_at_once_with_its_predicted_cost(tmp_path):
    """1,000 km at a stop a metre (about 1e6 stops): refused when the scenario loads, with the
    predicted time and memory; it used to print nothing for minutes while its simulation grew."""
    path = _scenario(tmp_path, lambda data: data["path"].update(
        waypoints=[[0.0, 0.0, 0.0], [1_000_000.0, 0.0, 0.0]], stop_spacing_m=[1.0, 1.0], sharp_turns=[]))
    with pytest.raises(ConfigError, match=r"1,000 km at 1-1 m a stop: about 1,000,000 stops, more than the 200,000 "
                                          r"a run takes \(predicted at least 2.7 h on 2 cores and a simulation that "
                                          r"grows past 27 GB"):
        load_scenario(path)
