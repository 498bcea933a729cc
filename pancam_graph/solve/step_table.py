"""One configuration's per-stop update results, kept as columns.

A StepResult per stop holds an object, a dict and a few numbers: about 250 bytes a stop and
configuration (tracemalloc, long_traverse), and the run's process holds every configuration's
for the whole traverse (mission_traverse: 33,589 stops, six configurations). As columns it is
the 8 bytes of each number, and those go to files as the traverse goes on (spill.Column): the
table is read only at the end.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from itertools import repeat

import numpy as np

from ..runtime.spill import Column
from .localizer import StepResult


class StepTable:
    """StepResults appended stop by stop and read back as they went in; the update times and
    stops as arrays. A counter keeps its type: whole numbers stay `int` (steps.csv writes them
    so) unless a stop gives it a fraction."""

    def __init__(self) -> None:
        self._stops = Column("q")
        self._update_ms = Column("d")
        self._relinearized = Column("q")
        self._counts: dict[str, Column] = {}  # name -> one value per stop, NaN where the stop did not set it
        self._whole: set[str] = set()  # counters every value of which was an int

    def append(self, step: StepResult) -> None:
        n = len(self._stops)
        for name, value in step.counts.items():
            if value is None:  # the same as not set: StepResult.count gives the declared default
                continue
            column = self._counts.get(name)
            if column is None:
                column = self._counts[name] = Column("d", repeat(math.nan, n))
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
        # each column read once, not a value at a time (files: a table is read at the end)
        counts = {name: column.to_numpy().tolist() for name, column in self._counts.items()}
        columns = zip(self._stops, self._update_ms, self._relinearized, strict=True)
        for i, (stop, ms, relinearized) in enumerate(columns):
            yield self._step(stop, ms, relinearized, {name: values[i] for name, values in counts.items()})

    def __getitem__(self, i: int) -> StepResult:
        return self._step(self._stops[i], self._update_ms[i], self._relinearized[i],
                          {name: column[i] for name, column in self._counts.items()})

    def _step(self, stop: int, ms: float, relinearized: int, values: dict[str, float]) -> StepResult:
        counts: dict[str, float | None] = {}
        for name, value in values.items():
            if not math.isnan(value):
                counts[name] = int(value) if name in self._whole else value
        return StepResult(stop, ms, relinearized, counts)

    @property
    def stops(self) -> np.ndarray:
        return self._stops.to_numpy()

    @property
    def update_ms(self) -> np.ndarray:
        return self._update_ms.to_numpy()

    @classmethod
    def of(cls, steps) -> StepTable:
        table = cls()
        for step in steps:
            table.append(step)
        return table
