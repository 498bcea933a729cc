"""When a group hands its state to the checkpoint writer (solve/housekeeping.py): at every site,
every CHECKPOINT_EVERY_STOPS, and at the first stop after CHECKPOINT_EVERY_S of work, so slow
stops are saved by the time they take, not only by their count."""

import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.solve import state as checkpoint_policy
from pancam_graph.solve.pipeline import RunOptions, run, simulated


class CountingSaver:
    """A checkpoint writer that records the stop each saved state goes on from."""

    def __init__(self, folder):
        self.next_stops: list[int] = []
        self.folder = folder

    def __call__(self, state):
        self.next_stops.append(state.next_stop)

    def part(self, index):
        return self

    def refer_to(self, traverse, truth):
        pass

    def log_folder(self, configuration):
        return self.folder / configuration


@pytest.fixture(scope="module")
def short():
    scenario = load_scenario(resolve_scenario("short_trail"))
    traverse, truth, resolved, info = simulated(scenario, 0)
    return traverse, truth, resolved


def _saves(short, monkeypatch, tmp_path, every_s: float) -> tuple[list[int], int]:
    traverse, truth, scenario = short
    monkeypatch.setattr(checkpoint_policy, "CHECKPOINT_EVERY_S", every_s)
    saver = CountingSaver(tmp_path)
    run(traverse, truth, scenario.estimator, 0, RunOptions(configs=("vo",)), save=saver)
    return saver.next_stops, len(traverse.stops)


def test_by_count_and_sites_when_stops_are_quick(short, monkeypatch, tmp_path):
    saved, stops = _saves(short, monkeypatch, tmp_path, 1e9)
    traverse = short[0]
    expected = [s.index + 1 for s in traverse.stops
                if (s.is_site or (s.index + 1) % checkpoint_policy.CHECKPOINT_EVERY_STOPS == 0) and s.index + 1 < stops]
    assert saved == expected and len(saved) < stops - 1


def test_by_time_at_every_stop_when_work_outlasts_the_interval(short, monkeypatch, tmp_path):
    saved, stops = _saves(short, monkeypatch, tmp_path, 0.0)
    assert saved == list(range(1, stops))  # every stop but the last (the end is the result itself)
