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



# The longest files (each over a minute of a 2-core machine's suite, site ties 88 + 39 s,
# the web viewer 66 s, the control field's calibration 30 s + its tests): started first.
LONGEST_FILES = ("frontend/test_site_ties.py", "viz/test_browser.py", "frontend/test_calibrate.py")


def pytest_collection_modifyitems(config, items):
    """The longest files first, then the other files with slow tests: pytest-xdist hands files to
    its workers in this order, so both start on the long ones and finish together, instead of one
    waiting alone on a long file collected last (the web viewer's, under viz/)."""
    def rank(item) -> int:
        path = item.path.as_posix()
        longest = [k for k, name in enumerate(LONGEST_FILES) if path.endswith(name)]
        return longest[0] if longest else len(LONGEST_FILES) + (item.path not in slow_files)

    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=rank)  # stable: each file's order stays
