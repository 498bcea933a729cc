"""The per-stop results as columns give back what went in."""

import pickle

import numpy as np
import pytest

from pancam_graph.runtime import spill
from pancam_graph.solve.localizer import StepResult
from pancam_graph.solve.step_table import StepTable


def _steps() -> list[StepResult]:
    return [
        StepResult(0, 0.5, 0, {}),
        StepResult(1, 1.25, 3, {"gps_fixes": 1, "gps_outliers": 0, "gps_mahalanobis2": 2.5}),
        StepResult(2, 0.75, 1, {"new_landmarks": 40, "rejected_ties": 2}),
        StepResult(3, 2.0, 7, {"gps_fixes": 2, "gps_outliers": 1, "gps_mahalanobis2": None, "vo_scale": 1.0}),
    ]


@pytest.mark.parametrize("in_files", [False, True])
def test_steps_read_back_as_they_went_in(monkeypatch, in_files):
    if in_files:  # all but the last stop in files of two stops (a column that starts late too)
        monkeypatch.setattr(spill, "CHUNK", 2)
    steps = _steps()
    table = StepTable.of(steps)
    back = list(pickle.loads(pickle.dumps(table)))  # and through a checkpoint
    assert len(table) == 4
    assert [table[i] for i in range(4)] == list(table)
    for want, got in zip(steps, back, strict=True):
        assert (got.stop, got.update_ms, got.relinearized) == (want.stop, want.update_ms, want.relinearized)
        assert got.counts == {k: v for k, v in want.counts.items() if v is not None}
        for name in ("gps_fixes", "new_landmarks", "gps_mahalanobis2", "sun_sightings"):
            assert got.count(name) == want.count(name)
            assert type(got.count(name)) is type(want.count(name))  # steps.csv writes an int without decimals


def test_a_counter_given_a_fraction_is_read_as_floats():
    table = StepTable.of([StepResult(0, 0.1, 0, {"vo_scale": 1}), StepResult(1, 0.1, 0, {"vo_scale": 0.5})])
    assert [s.count("vo_scale") for s in table] == [1.0, 0.5]
    assert all(type(s.count("vo_scale")) is float for s in table)


def test_columns():
    table = StepTable.of(_steps())
    np.testing.assert_array_equal(table.stops, [0, 1, 2, 3])
    np.testing.assert_array_equal(table.update_ms, [0.5, 1.25, 0.75, 2.0])
    assert table[2].counts == {"new_landmarks": 40, "rejected_ties": 2}
    empty = StepTable()
    assert len(empty) == 0 and empty.update_ms.shape == (0,) and list(empty) == []
