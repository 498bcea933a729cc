"""A group's image records (panoramas, HRC frames, ground patches) in a file, read a stop at a
time: a worker holds a site's panorama while it steps that site, not the traverse's."""

from __future__ import annotations

import pickle
from dataclasses import replace
from pathlib import Path

from ..errors import GraphError
from ..records import Stop, Traverse


class StopRecords:
    """The image records a group reads (panoramas, HRC frames, ground patches) in a file, one
    pickle a stop: its worker reads a stop's as it comes to it and holds none for the rest of
    the traverse (a mission's panoramas are a hundred MB pickled)."""

    def __init__(self, path: Path, offsets: dict[int, int]):
        self.path = path
        self.offsets = offsets  # stop -> where its records start in the file

    @staticmethod
    def write(path: Path, traverse: Traverse, fields: set[str]) -> StopRecords:
        offsets = {}
        with open(path, "wb") as f:
            for k, stop in enumerate(traverse.stops):
                records = {name: getattr(stop, name) for name in sorted(fields)}
                records = {name: value for name, value in records.items() if value is not None and value != ()}
                if records:
                    offsets[k] = f.tell()
                    pickle.dump(records, f, protocol=pickle.HIGHEST_PROTOCOL)
        return StopRecords(path, offsets)

    def attach(self, k: int, stop: Stop) -> Stop:
        """Stop k with its records, read from the file."""
        at = self.offsets.get(k)
        if at is None:
            return stop
        try:
            with open(self.path, "rb") as f:
                f.seek(at)
                records = pickle.load(f)
        except (OSError, EOFError, pickle.UnpicklingError) as exc:
            raise GraphError(f"{self.path}: the image records of stop {k} cannot be read back: {exc}") from None
        return replace(stop, **records)
