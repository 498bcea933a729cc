"""What the smoother keeps of the variables that left its window: a row of numbers a variable
(its estimate as it left, or its pose's marginal position covariance), the latest rows in
memory and every `CHUNK_ROWS` of them in files mapped read-only, so the run's memory does not
grow with the traverse (a `gtsam.Values` holds every variable in memory).

The files are unlinked once mapped (spill.mapped): nothing is left behind, however the run
ends; a checkpoint carries their rows."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import gtsam
import numpy as np

from ..runtime.spill import mapped
from .keys import value_type

# rows a file; the environment may set it (tests). The rows in memory before they go are the
# sawtooth of a group's memory along the mission (docs/performance.md)
CHUNK_ROWS = int(os.environ.get("PANCAM_GRAPH_FROZEN_CHUNK_ROWS", "4096"))
_SYMBOL_SHIFT = 56  # a gtsam.Symbol's character is the key's top byte


@dataclass(frozen=True)
class _Chunk:
    """Rows sorted by key: row i is data[offsets[i]:offsets[i + 1]]."""

    keys: np.ndarray  # (n,) int64, sorted
    offsets: np.ndarray  # (n + 1,) int64
    data: np.ndarray  # float64
    ranges: dict[int, tuple[int, int]]  # symbol character -> (smallest key, largest key) with it

    @classmethod
    def of(cls, keys: np.ndarray, offsets: np.ndarray, data: np.ndarray) -> _Chunk:
        ranges = {}
        for symbol in np.unique(keys >> _SYMBOL_SHIFT):
            these = keys[(keys >> _SYMBOL_SHIFT) == symbol]
            ranges[int(symbol)] = (int(these[0]), int(these[-1]))
        return cls(keys, offsets, data, ranges)

    def find(self, key: int) -> int:
        """The row of `key`, or -1."""
        bounds = self.ranges.get(key >> _SYMBOL_SHIFT)
        if bounds is None or not bounds[0] <= key <= bounds[1]:
            return -1
        i = int(np.searchsorted(self.keys, key))
        return i if i < len(self.keys) and self.keys[i] == key else -1

    def row(self, i: int) -> np.ndarray:
        return self.data[self.offsets[i]:self.offsets[i + 1]]


class FrozenRows:
    """Rows of numbers by variable key, for variables that left the window. A key put again
    before its rows go to a file (a replay freezing the same variables) replaces its row."""

    def __init__(self) -> None:
        # the latest rows, one after another in one block, filled and emptied again and again
        # (a small array a row, kept until its file, scattered the heap's free space)
        self._tail: dict[int, tuple[int, int]] = {}  # key -> (start, width) in the block
        self._block = np.zeros(0)
        self._used = 0
        self._chunks: list[_Chunk] = []

    @property
    def files(self) -> int:
        """Chunks of rows written to files so far."""
        return len(self._chunks)

    def __len__(self) -> int:
        return len(self._tail) + sum(len(c.keys) for c in self._chunks)

    def put(self, key: int, row: np.ndarray) -> None:
        row = np.asarray(row, dtype=float).ravel()
        at = self._tail.get(key)
        if at is None or at[1] != len(row):
            if self._used + len(row) > len(self._block):
                grown = np.empty(max(2 * len(self._block), CHUNK_ROWS * 12, self._used + len(row)))
                grown[:self._used] = self._block[:self._used]
                self._block = grown
            at = self._tail[key] = (self._used, len(row))
            self._used += len(row)
        self._block[at[0]:at[0] + at[1]] = row

    def _tail_row(self, key: int) -> np.ndarray | None:
        at = self._tail.get(key)
        return None if at is None else self._block[at[0]:at[0] + at[1]].copy()  # the block is reused

    def get(self, key: int) -> np.ndarray | None:
        row = self._tail_row(key)
        if row is not None:
            return row
        for chunk in reversed(self._chunks):
            i = chunk.find(key)
            if i >= 0:
                return chunk.row(i)
        return None

    def __contains__(self, key: int) -> bool:
        return self.get(key) is not None

    def items(self) -> Iterator[tuple[int, np.ndarray]]:
        for chunk in self._chunks:
            for i, key in enumerate(chunk.keys.tolist()):
                yield key, chunk.row(i)
        for key in list(self._tail):
            yield key, self._tail_row(key)

    def rows(self, keys: list[int], width: int) -> tuple[np.ndarray, np.ndarray]:
        """(found, rows): whether each key is here and its row (rows of `width` numbers; zeros
        where not found), looked up together."""
        wanted = np.asarray(keys, dtype=np.int64)
        found = np.zeros(len(wanted), dtype=bool)
        out = np.zeros((len(wanted), width))
        for chunk in self._chunks:
            if not len(chunk.keys):
                continue
            i = np.minimum(np.searchsorted(chunk.keys, wanted), len(chunk.keys) - 1)
            hit = (chunk.keys[i] == wanted) & ~found
            start = chunk.offsets[i[hit]]
            out[hit] = chunk.data[start[:, None] + np.arange(width)]
            found |= hit
        for j in np.flatnonzero(~found):
            row = self._tail_row(int(wanted[j]))
            if row is not None:
                out[j], found[j] = row, True
        return found, out

    def write_full(self) -> None:
        """The latest rows to a file once there are `CHUNK_ROWS` of them. Only when none will be
        put again (after a successful update)."""
        if len(self._tail) < CHUNK_ROWS:
            return
        keys = np.fromiter(self._tail, dtype=np.int64, count=len(self._tail))
        order = np.argsort(keys)
        spans = np.array(list(self._tail.values()), dtype=np.int64).reshape(-1, 2)[order]
        offsets = np.concatenate([[0], np.cumsum(spans[:, 1])])
        data = np.concatenate([self._block[start:start + width] for start, width in spans.tolist()])
        self._chunks.append(_Chunk.of(mapped(keys[order]), mapped(offsets), mapped(data)))
        self._tail, self._used = {}, 0

    # -- checkpoints: the rows themselves, mapped again from new files ------------------------

    def __getstate__(self) -> dict:
        return {"tail": {key: self._tail_row(key) for key in self._tail},
                "chunks": [(np.asarray(c.keys), np.asarray(c.offsets), np.asarray(c.data)) for c in self._chunks]}

    def __setstate__(self, state: dict) -> None:
        self.__init__()
        for key, row in state["tail"].items():
            self.put(key, row)
        self._chunks = [_Chunk.of(mapped(keys), mapped(offsets), mapped(data))
                        for keys, offsets, data in state["chunks"]]


# -- a variable's value as a row and back, by its kind of variable (keys.value_type) --------------

def row_of(values: gtsam.Values, key: int) -> np.ndarray:
    kind = value_type(key)
    if kind == "Pose3":
        return values.atPose3(key).matrix()[:3].ravel()  # rotation and translation, 3x4
    if kind == "Double":
        return np.array([values.atDouble(key)])
    return np.asarray(getattr(values, f"at{kind}")(key), dtype=float)


def pose_matrices(rows: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses from (N, 12) rows of their 3x4 [R | t], row by row (`row_of`'s,
    `Smoother.stacked`'s, a KITTI pose file's)."""
    out = np.zeros((len(rows), 4, 4))
    out[:, :3] = np.asarray(rows).reshape(-1, 3, 4)
    out[:, 3, 3] = 1.0
    return out


def value_of(key: int, row: np.ndarray):
    """The GTSAM value (Pose3, a float, or an array for a Point3 or a Vector) of `row`."""
    kind = value_type(key)
    if kind == "Pose3":
        return gtsam.Pose3(np.vstack([row.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]]))
    if kind == "Double":
        return float(row[0])
    return np.array(row)
