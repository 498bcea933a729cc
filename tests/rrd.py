"""Read a saved rerun recording back with rerun's own reader (test helper)."""

from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader


class Recording:
    """Rows per entity path: static rows, and temporal rows ordered by the `stop` timeline."""

    def __init__(self, path: Path):
        self.static: dict[str, dict] = defaultdict(dict)
        self.temporal: dict[str, list[tuple[int, dict]]] = defaultdict(list)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a killed run's file has no footer: rerun warns, then scans
            chunks = RrdReader(str(path)).stream().to_chunks()
        for chunk in chunks:
            batch = chunk.to_record_batch()
            data = [n for n in batch.schema.names if ":" in n]
            columns = {n: batch.column(n).to_pylist() for n in data}
            stops = batch.column("stop").to_pylist() if "stop" in batch.schema.names else None
            for i in range(batch.num_rows):
                row = {n: columns[n][i] for n in data if columns[n][i] is not None}
                if stops is None:
                    self.static[chunk.entity_path].update(row)
                else:
                    self.temporal[chunk.entity_path].append((stops[i], row))
        for rows in self.temporal.values():
            rows.sort(key=lambda r: r[0])  # stable: within a stop, logging order is kept

    @property
    def entity_paths(self) -> set[str]:
        return set(self.static) | set(self.temporal)

    def at(self, path: str, stop: int, component: str):
        """Latest value of a component logged at exactly `stop` (None if none)."""
        values = [row[component] for s, row in self.temporal[path] if s == stop and component in row]
        return values[-1] if values else None

    def latest(self, path: str, component: str):
        """Latest-at value over the whole recording, as a viewer shows it at the end."""
        for _, row in reversed(self.temporal[path]):
            if component in row:
                return row[component]
        return self.static[path].get(component)

    def stops(self, path: str) -> list[int]:
        return [s for s, _ in self.temporal[path]]


def array(value) -> np.ndarray:
    return np.asarray(value, dtype=float)
