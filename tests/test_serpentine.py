"""A generated serpentine path: its shape, its length, and its round trip through a run's
run.toml (which writes the waypoints out beside the serpentine)."""

import tomllib

import numpy as np
import pytest
from pydantic import ValidationError

from pancam_graph.config import Scenario, Serpentine, dump_scenario, load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError
from pancam_graph.sim.world import dense_path


def test_legs_alternate_with_sharp_turns_at_their_ends():
    waypoints, turns = Serpentine(legs=3, leg_m=300.0, spacing_m=50.0, wiggle_m=5.0, relief_m=2.0).waypoints()
    w = np.array(waypoints)
    assert len(w) == 12
    np.testing.assert_allclose(w[[0, 3, 4, 7, 8, 11], 0], [0, 300, 300, 0, 0, 300])  # east, west, east
    np.testing.assert_allclose(w[[0, 3, 4, 7, 8, 11], 1], [0, 0, 50, 50, 100, 100])
    assert np.all(np.abs(w[:, 1] - np.repeat([0, 50, 100], 4)) <= 5.0)  # bends aside at the thirds
    assert np.all(np.abs(w[:, 2]) <= 2.0)
    assert turns == [3, 4, 7, 8]


def test_mission_traverse_is_about_fifty_km():
    scenario = load_scenario(resolve_scenario("mission_traverse"))
    assert 45_000.0 < dense_path(scenario.path).length_m < 55_000.0
    assert len(scenario.path.sharp_turns) == 2 * 48 - 2


def test_round_trip_through_run_toml_and_conflicting_waypoints_refused():
    scenario = load_scenario(resolve_scenario("mission_traverse"))
    data = tomllib.loads(dump_scenario(scenario))
    assert "waypoints" in data["path"] and "serpentine" in data["path"]
    assert Scenario.model_validate(data).path == scenario.path
    data["path"]["waypoints"][5][0] += 1.0
    with pytest.raises(ValidationError, match="waypoints and sharp_turns or a serpentine, not both"):
        Scenario.model_validate(data)


def test_bad_serpentine_names_its_field(tmp_path):
    text = resolve_scenario("mission_traverse").read_text().replace("legs = 48", "legs = 0")
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match="serpentine.legs"):
        load_scenario(path)
