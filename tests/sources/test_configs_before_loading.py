"""`--configs` is checked against the source's own configurations before the source loads: a
typo on an image folder costs no front-end run (issue 59's papercut), and a scenario's or a
folder's own configurations count."""

import pytest

from pancam_graph import api
from pancam_graph.config import dump_scenario, load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError, FrameError
from pancam_graph.sim import simulate
from pancam_graph.store.observation_writer import write_observations


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory):
    """short_trail as an image folder whose images are not there: the front-end, once it runs,
    stops at the first one."""
    scenario = load_scenario(resolve_scenario("short_trail"))
    estimator = scenario.estimator.model_copy(update={
        "configurations": {**scenario.estimator.configurations, "my_vo": ["vo"]}})
    traverse, truth = simulate(scenario, 0)
    frames = [(f"images/{k:06d}_left.png", f"images/{k:06d}_right.png") for k in range(len(traverse.stops))]
    folder = tmp_path_factory.mktemp("configs") / "images"
    write_observations(folder, traverse, estimator, 0, truth, scenario.rig, frames=frames)
    return folder


def test_a_configuration_typo_is_refused_before_the_front_end_runs(image_folder, tmp_path):
    with pytest.raises(ConfigError, match="--configs vo_site: .*did you mean vo_sites"):
        api.run(image_folder, configs=("vo_site",), out=tmp_path / "typo", processes=1)
    with pytest.raises(ConfigError, match="'hrc' needs 'sites'"):
        api.run(image_folder, configs=("vo", "hrc+vo"), out=tmp_path / "kinds", processes=1)
    assert list(tmp_path.iterdir()) == []  # nothing written
    # the folder's own configuration passes the early check: the front-end runs and stops at
    # the first missing image (the control, showing the check came first above)
    with pytest.raises(FrameError, match="000000_left.png"):
        api.run(image_folder, configs=("my_vo",), out=tmp_path / "own", processes=1)


def test_a_scenarios_own_configurations_pass_and_others_are_refused(tmp_path):
    scenario = load_scenario(resolve_scenario("short_trail"))
    estimator = scenario.estimator.model_copy(update={"configurations": {"my_vo": ["vo"]}})
    path = tmp_path / "own.toml"
    path.write_text(dump_scenario(scenario.model_copy(update={"estimator": estimator})), encoding="utf-8")
    api.check_configs(path, ("my_vo", "vo+gps"))
    with pytest.raises(ConfigError, match="--configs my_v: .*did you mean my_vo"):
        api.check_configs(path, ("my_v",))
    with pytest.raises(ConfigError, match="--configs full_mar: .*did you mean full_mars"):
        api.check_configs("mars_excerpt", ("vo", "full_mar"))


def test_a_source_whose_configurations_loading_tells_is_checked_once_loaded():
    """A bag's configurations depend on its topics (stereo or not): no early verdict."""
    from pathlib import Path

    bag = Path(__file__).parents[1] / "data" / "real" / "robot_localization" / "test1.bag"
    api.check_configs(bag, ("anything",))  # refused by select_configurations after loading
