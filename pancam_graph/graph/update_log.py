"""A smoother's update log: every update's new factors, the initial values it inserted and
their clocks, in order. The newest updates are kept in memory; every `CHUNK_UPDATES` of them
go to a file, so the log does not hold the whole traverse in memory. Read back in
order, it rebuilds the smoother (checkpoints, the Cholesky-to-QR fallback) and gives the
bound (CRLB) and the batch polish their graph.

A run that checkpoints keeps its log's files beside its checkpoint (`keep_in`), where a
saved state refers to them; other runs keep them in a temporary folder that goes when the
log does.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gtsam

from ..errors import GraphError
from ..runtime.atomic import write_atomically
from ..runtime.scratch import temporary_folder
from .keys import subset

# updates per file (denver_trail's ~900 stops make one and a tail); the environment may set it
CHUNK_UPDATES = int(os.environ.get("PANCAM_GRAPH_LOG_CHUNK_UPDATES", "500"))

# How to make a factor again: (function, arguments). Python CustomFactors do not pickle.
Rebuild = tuple[Callable[..., gtsam.NonlinearFactor], tuple[Any, ...]]


@dataclass
class Update:
    """One update of the smoother: its new factors (the recipes of its CustomFactors by index
    among them), the initial values it inserted and the clock of each key it stamped."""

    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    stamps: dict[int, float]
    rebuild: dict[int, Rebuild]
    removed: list[int] = dataclasses.field(default_factory=list)  # iSAM2 factor indices it removed
    # the same factors as (update, position among its new factors): the graph without them
    replaced: list[tuple[int, int]] = dataclasses.field(default_factory=list)


class _Updates:
    """Updates pickled together: their factors as one graph and their values as one Values,
    which GTSAM serializes in a fraction of the time of each update's own (boost text archives;
    a CustomFactor as its recipe)."""

    def __init__(self, updates: list[Update]):
        self.updates = updates

    def __getstate__(self) -> dict:
        plain, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for update in self.updates:
            for i in range(update.factors.size()):
                if i not in update.rebuild:
                    plain.add(update.factors.at(i))
            values.insert(update.values)
        values, scalars = picklable(values)
        shapes = [(u.factors.size(), u.rebuild, list(u.values.keys()), u.stamps, u.removed, u.replaced)
                  for u in self.updates]
        return {"plain": plain, "values": values, "scalars": scalars, "shapes": shapes}

    def __setstate__(self, state: dict) -> None:
        plain, values = state["plain"], with_scalars(state["values"], state["scalars"])
        self.updates, taken = [], 0
        for count, rebuild, keys, stamps, removed, replaced in state["shapes"]:
            factors = gtsam.NonlinearFactorGraph()
            for i in range(count):
                if i in rebuild:
                    function, arguments = rebuild[i]
                    factors.add(function(*arguments))
                else:
                    factors.add(plain.at(taken))
                    taken += 1
            self.updates.append(Update(factors, subset(values, keys), stamps, rebuild, removed, replaced))


class UpdateLog:
    """Every update of a smoother, in order: the last ones in memory, the rest in files of
    `CHUNK_UPDATES` updates."""

    def __init__(self) -> None:
        self._temporary: tempfile.TemporaryDirectory | None = None
        self._folder: Path | None = None  # made when the first file is written
        self.files = 0  # chunk files written (chunk-00000.pkl ...)
        self.tail: list[Update] = []  # the updates after them
        self.factor_count = 0
        self.update_count = 0

    def append(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
               rebuild: dict[int, Rebuild], removed: list[int] | None = None,
               replaced: list[tuple[int, int]] | None = None) -> None:
        self.tail.append(Update(factors, values, stamps, rebuild, list(removed or []), list(replaced or [])))
        self.factor_count += factors.size()
        self.update_count += 1
        if len(self.tail) >= CHUNK_UPDATES:
            self._write_chunk()

    def __iter__(self) -> Iterator[Update]:
        for index in range(self.files):
            yield from self._read_chunk(index)
        yield from self.tail

    def all_factors(self) -> gtsam.NonlinearFactorGraph:
        """Every factor ever added and not replaced, in order (the whole traverse's graph: it all
        comes into memory)."""
        graph = gtsam.NonlinearFactorGraph()
        for update in self.kept():
            graph.push_back(update.factors)
        return graph

    def kept(self) -> Iterator[Update]:
        """The updates with the factors a later update replaced taken out of them (the graph as
        it stands: for the batch polish and the bound, which build it anew)."""
        replaced: defaultdict[int, set[int]] = defaultdict(set)  # update -> its positions replaced later
        for update in self:
            for number, position in update.replaced:
                replaced[number].add(position)
        for number, update in enumerate(self):
            if number in replaced:
                factors = gtsam.NonlinearFactorGraph()
                for position in range(update.factors.size()):
                    if position not in replaced[number]:
                        factors.add(update.factors.at(position))
                update = dataclasses.replace(update, factors=factors)
            yield update

    def keep_in(self, folder: Path) -> None:
        """Write this log's files to `folder` from now on (a run's checkpoint, which refers to
        them), with those written so far."""
        folder = Path(folder).resolve()  # a saved state refers to it from wherever it is read
        if self._folder is not None and folder.resolve() == self._folder.resolve():
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
            for index in range(self.files):
                shutil.copyfile(self._path(index), folder / _chunk_name(index))
        except OSError as exc:
            raise GraphError(f"{folder}: cannot keep the smoother's update log there: {exc.strerror}") from None
        self._folder, self._temporary = folder, None  # a temporary folder goes with its object

    # -- files ---------------------------------------------------------------------------------

    def _path(self, index: int) -> Path:
        assert self._folder is not None
        return self._folder / _chunk_name(index)

    def _write_chunk(self) -> None:
        if self._folder is None:
            self._temporary = temporary_folder("log")
            self._folder = Path(self._temporary.name)
        path = self._path(self.files)
        try:  # a checkpoint's log must be on disk if a saved state refers to it
            write_atomically(path, lambda f: pickle.dump(_Updates(self.tail), f, protocol=pickle.HIGHEST_PROTOCOL),
                             durable=self._temporary is None)
        except OSError as exc:
            raise GraphError(f"{path}: cannot write the smoother's update log: {exc.strerror}") from None
        self.files += 1
        self.tail = []

    def _read_chunk(self, index: int) -> list[Update]:
        path = self._path(index)
        try:
            with path.open("rb") as f:
                return pickle.load(f).updates
        except OSError as exc:
            raise GraphError(f"{path}: cannot read the smoother's update log: {exc.strerror}") from None
        except Exception as exc:  # a truncated or foreign file: pickle raises many kinds of errors
            raise GraphError(f"{path}: not a readable update log ({type(exc).__name__}: {exc})") from None

    # -- checkpoints ---------------------------------------------------------------------------

    def __getstate__(self) -> dict:
        """A log kept in a run's folder refers to its files; a temporary one carries them."""
        state = {k: v for k, v in vars(self).items() if k not in ("_temporary", "_folder")}
        state["tail"] = _Updates(self.tail)
        if self._temporary is None and self._folder is not None:
            state["folder"] = str(self._folder)
        else:
            state["chunks"] = [self._path(index).read_bytes() for index in range(self.files)]
        return state

    def __setstate__(self, state: dict) -> None:
        chunks = state.pop("chunks", None)
        folder = state.pop("folder", None)
        vars(self).update(state)
        self.tail = self.tail.updates
        self._temporary, self._folder = None, None if folder is None else Path(folder)
        if chunks is not None:
            self.files = 0
            if chunks:
                self._temporary = temporary_folder("log")
                self._folder = Path(self._temporary.name)
            for blob in chunks:
                self._path(self.files).write_bytes(blob)
                self.files += 1
        else:
            missing = [i for i in range(self.files) if not self._path(i).is_file()]
            if missing:
                raise GraphError(f"{self._path(missing[0])}: the smoother's update log is missing (the checkpoint "
                                 "refers to it; was the run's folder moved?)")


def _chunk_name(index: int) -> str:
    return f"chunk-{index:05d}.pkl"


def picklable(values: gtsam.Values) -> tuple[gtsam.Values, dict[int, float]]:
    """Values pickle, except scalars (GTSAM does not register them for serialization): those
    are taken out as floats."""
    scalars = {}
    for key in values.keys():
        try:
            scalars[key] = values.atDouble(key)
        except RuntimeError:  # not a scalar
            pass
    if not scalars:
        return values, scalars
    others = gtsam.Values(values)
    for key in scalars:
        others.erase(key)
    return others, scalars


def with_scalars(values: gtsam.Values, scalars: dict[int, float]) -> gtsam.Values:
    for key, value in scalars.items():
        values.insert(key, value)
    return values
