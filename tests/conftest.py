import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.solve.pipeline import RunOptions, run_scenario


@pytest.fixture(scope="session")
def short_scenario():
    """short_trail on the ideal simulator: the tests of a mechanism (a window, a gate, a resume)
    take the traverse their figures were measured on; the realistic profile, the bundled
    scenarios' own, has tests of its own (tests/sim/test_errors.py, tests/kinds/)."""
    return load_scenario(resolve_scenario("short_trail"), errors="ideal")


@pytest.fixture(scope="session")
def short_run(short_scenario):
    """All four configurations of the short scenario, seed 0 (shared by several tests)."""
    return run_scenario(short_scenario, RunOptions(seed=0))
