"""One configuration's per-stop update results, kept as columns.

A StepResult per stop holds an object, a dict and a few numbers: about 250 bytes a stop and
configuration (tracemalloc, long_traverse), and the run's process holds every configuration's
for the whole traverse (mission_traverse: 33,589 stops, six configurations). As columns it is
the 8 bytes of each number.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterator

import numpy as np

from .localizer import StepResult


class StepTable:
    """StepResults appended stop by stop and read back as they went in; the update times and
    stops as arrays. A counter keeps its type: whole numbers stay `int` (steps.csv writes them
    so) unless a stop gives it a fraction."""

    def __init__(self) -> None:
        self._stops = array("q")
        self._update_ms = array("d")
        self._relinearized = array("q")
        self._counts: dict[str, array] = {}  # name -> one value per stop, NaN where the stop did not set it
        self._whole: set[str] = set()  # counters every value of which was an int

    def append(self, step: StepResult) -> None:
        n = len(self._stops)
        for name, value in step.counts.items():
            if value is None:  # the same as not set: StepResult.count gives the declared default
                continue
            column = self._counts.get(name)
            if column is None:
                column = self._counts[name] = array("d", [math.nan]) * n
                if type(value) is int:
                    self._whole.add(name)
            elif type(value) is not int:
                self._whole.discard(name)
            column.append(float(value))
        for column in self._counts.values():
            if len(column) == n:
                column.append(math.nan)
        self._stops.append(step.stop)
        self._update_ms.append(step.update_ms)
        self._relinearized.append(step.relinearized)

    def __len__(self) -> int:
        return len(self._stops)

    def __iter__(self) -> Iterator[StepResult]:
        for i in range(len(self._stops)):
            yield self[i]

    def __getitem__(self, i: int) -> StepResult:
        counts: dict[str, float | None] = {}
        for name, column in self._counts.items():
            value = column[i]
            if not math.isnan(value):
                counts[name] = int(value) if name in self._whole else value
        return StepResult(self._stops[i], self._update_ms[i], self._relinearized[i], counts)

    @property
    def stops(self) -> np.ndarray:
        return np.frombuffer(self._stops, dtype=np.int64).copy()

    @property
    def update_ms(self) -> np.ndarray:
        return np.frombuffer(self._update_ms, dtype=np.float64).copy()

    @classmethod
    def of(cls, steps) -> StepTable:
        table = cls()
        for step in steps:
            table.append(step)
        return table
