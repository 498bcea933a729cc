from pathlib import Path

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


# `./dev.sh test` runs two test processes that take a file at a time, in collection order
# (pytest-xdist's loadfile): the longest files go first, so that what is left to hand out at the
# end is short and both processes finish together. Measured (one quiet suite): these ten are
# 20-100 s each; the other files keep their order behind them. A stale list costs only balance.
LONGEST_FIRST = ("frontend/test_site_ties.py", "cli/test_cli_mistakes.py", "solve/test_end_to_end.py",
                 "api/test_resume.py", "render/test_render.py", "viz/test_browser.py", "frontend/test_calibrate.py",
                 "cli/test_bad_maps.py", "sweep/test_sweep.py", "kinds/test_orbital.py")
_TESTS = Path(__file__).parent


def pytest_collection_modifyitems(config, items):
    def rank(item) -> int:
        try:
            name = item.path.relative_to(_TESTS).as_posix()
        except ValueError:
            return len(LONGEST_FIRST)
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: a file's tests keep their order
