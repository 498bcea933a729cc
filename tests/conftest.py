import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.solve.pipeline import RunOptions, run_scenario


@pytest.fixture(scope="session")
def short_scenario():
    return load_scenario(resolve_scenario("short_trail"))


@pytest.fixture(scope="session")
def short_run(short_scenario):
    """All four configurations of the short scenario, seed 0 (shared by several tests)."""
    return run_scenario(short_scenario, RunOptions(seed=0))
