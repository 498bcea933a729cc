"""A run's checkpoints in its staging folder, so a killed run can go on (`run --resume`).

The run's inputs are written once; its state (solve.state.RunState) at checkpoints, one file per
group of configurations when groups run side by side (each group's process writes its own).
Each file is written whole under a temporary name and renamed into place, so a kill at any
moment leaves the last complete checkpoint. The state refers to the inputs' traverse, stops and truth by
name instead of copying them (pickle's persistent ids): a checkpoint holds only what the run
built. Saving costs time that grows with the graph, so a state is saved at most every
`min_interval_s` and never more than `max_overhead` of the run's time (0: at every checkpoint).
"""

from __future__ import annotations

import copy
import pickle
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Protocol

from ..errors import ResultsError, WriteFailed
from ..runtime.atomic import write_atomically

if TYPE_CHECKING:
    from ..records import GroundTruth, Traverse
    from ..solve.results import RunOptions
    from ..solve.state import RunState

CHECKPOINT_DIR = "checkpoint"
INPUTS_FILE = "inputs.pkl"
STATE_FILE = "state.pkl"  # a run in one process; side by side, group g's is state-g.pkl
STATE_HEADER = "pancam-graph state; next stop"
FORMAT = 13  # a checkpoint of another format is refused, not misread (2: the smoother's window; 3: groups;
# 4: the partial relinearization check; 5: the smoothers' update logs in files beside the states;
# 6: the run loop's classes in pancam_graph.solve; 7: per-stop results and tie links as columns;
# 8: the variables that left the window as rows, graph.frozen; 9: the motions as columns;
# 10: the per-stop columns, stops, views and landmark tracks in files, spill.Column; 11: modules moved into
# geometry/, runtime/ and orbital/, shared scalars numbered by graph.keys.shared; 12: SourceData in sources/;
# 13: the motions' calibration sensitivity)
LOG_DIR = "log"  # the smoothers' update logs, one folder per configuration


class SourceInputs(Protocol):
    """What a checkpoint needs of the source's data (sources.registry.SourceData, which lives
    above the store): the traverse and truth its states refer to by name."""

    traverse: Traverse
    truth: GroundTruth | None


@dataclass(frozen=True)
class RunInputs:
    """What the run was started with: the source's data and the run options."""

    data: SourceInputs
    options: RunOptions
    format: int = FORMAT


class CheckpointWriter:
    """Called by the run loop at every checkpoint with the run's state."""

    def __init__(self, folder: Path, inputs: RunInputs, min_interval_s: float = 30.0, max_overhead: float = 0.05,
                 resumed: bool = False):
        """`resumed`: the writer of a resumed run (its inputs and states are there)."""
        self.folder = Path(folder) / CHECKPOINT_DIR
        self.state_file = STATE_FILE
        self.parts: list[str] = []  # the state files of the groups handed out by `part`
        self.shared = _named(inputs.data.traverse, inputs.data.truth)
        self.min_interval_s = min_interval_s
        self.max_overhead = max_overhead
        self.saves = 0
        self.save_s = 0.0
        self._last_end = time.perf_counter()
        self._last_cost = 0.0
        try:
            self.folder.mkdir(exist_ok=True)
        except OSError as exc:
            raise ResultsError(f"{self.folder}: cannot create the checkpoint folder: {exc.strerror}") from None
        if not resumed:
            _write_atomically(self.folder / INPUTS_FILE, lambda f: _Pickler(f, {}).dump(inputs))

    def __call__(self, state: RunState) -> None:
        since = time.perf_counter() - self._last_end
        if self.min_interval_s > 0 and since < max(self.min_interval_s, self._last_cost / self.max_overhead):
            return
        start = time.perf_counter()
        # the stop first, in plain text: whoever must say where the run would go on reads just that
        # (a group's process saves its own states; the run's process only reads them)
        header = f"{STATE_HEADER} {state.next_stop}\n".encode()

        def write(f) -> None:
            f.write(header)
            _Pickler(f, self.shared).dump(state)

        _write_atomically(self.folder / self.state_file, write)
        self._last_end = time.perf_counter()
        self._last_cost = self._last_end - start
        self.saves += 1
        self.save_s += self._last_cost

    def part(self, index: int) -> CheckpointWriter:
        """The writer of group `index`'s states (pickled to the group's process with the run's
        inputs, which its states refer to)."""
        writer = copy.copy(self)
        writer.state_file = f"state-{index}.pkl"
        writer.parts = []
        self.parts.append(writer.state_file)
        return writer

    def __getstate__(self) -> dict[str, Any]:
        # A group's writer goes to its process without the inputs: that process names its own
        # traverse (refer_to); sent along, they were the whole traverse again in every worker.
        return {**self.__dict__, "shared": {}}

    def refer_to(self, traverse: Traverse, truth: GroundTruth | None) -> None:
        """Name `traverse` (a group process's own, without the image records it does not read)
        and its stops and `truth` in the states, as the inputs name theirs: a resumed run finds
        them in the inputs."""
        self.shared = _named(traverse, truth)

    def log_folder(self, configuration: str) -> Path:
        """Where a configuration's smoother writes its update log, which the states refer to."""
        return self.folder / LOG_DIR / configuration

    @property
    def saved_stops(self) -> list[int]:
        """The stop each group would go on from, as saved on disk (empty: nothing saved yet; a
        group that saved nothing starts again, at 0)."""
        stops = [saved_stop(self.folder / name) for name in (self.parts or [self.state_file])]
        return [stop or 0 for stop in stops] if any(stop is not None for stop in stops) else []


def read_checkpoint(folder: Path) -> tuple[RunInputs, list[RunState]]:
    """The inputs and last saved states (one per group of configurations) of the run whose
    staging folder is `folder`."""
    where = Path(folder) / CHECKPOINT_DIR
    inputs_path = where / INPUTS_FILE
    state_paths = sorted(where.glob("state*.pkl"), key=lambda p: (len(p.name), p.name))
    if not state_paths:
        saved = "has its inputs but no state yet (killed before its first checkpoint was saved)" \
            if inputs_path.is_file() else "has no checkpoint"
        raise ResultsError(f"{folder}: {saved}; start the run again")
    inputs = _loads(inputs_path, {})
    if not isinstance(inputs, RunInputs) or inputs.format != FORMAT:
        raise ResultsError(f"{inputs_path}: not a checkpoint of this version of pancam-graph")
    shared = _named(inputs.data.traverse, inputs.data.truth)
    return inputs, [_loads(path, shared, header=True) for path in state_paths]


def remove_checkpoint(folder: Path) -> None:
    """A finished run's checkpoint is of no more use (and would be the largest file of its results)."""
    shutil.rmtree(Path(folder) / CHECKPOINT_DIR, ignore_errors=True)


def _named(traverse: Traverse, truth: GroundTruth | None) -> dict[str, Any]:
    """The input objects a state refers to, by name."""
    named: dict[str, Any] = {"traverse": traverse, "truth": truth}
    for k, stop in enumerate(traverse.stops):
        named[f"stop/{k}"] = stop
    return {name: obj for name, obj in named.items() if obj is not None}


class _Pickler(pickle.Pickler):
    def __init__(self, file, shared: dict[str, Any]):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._names = {id(obj): name for name, obj in shared.items()}

    def persistent_id(self, obj):
        return self._names.get(id(obj))


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, shared: dict[str, Any]):
        super().__init__(file)
        self._shared = shared

    def persistent_load(self, pid):
        try:
            return self._shared[pid]
        except KeyError:
            raise pickle.UnpicklingError(f"refers to {pid!r}, which the run's inputs do not have") from None


def saved_stop(path: Path) -> int | None:
    """The stop a saved state goes on from, from its first line (None: no state there)."""
    try:
        with path.open("rb") as f:
            line = f.readline(200).decode("ascii", "replace")
    except OSError:
        return None
    head, _, stop = line.rpartition(" ")
    return int(stop) if head == STATE_HEADER and stop.strip().isdigit() else None


def _loads(path: Path, shared: dict[str, Any], header: bool = False):
    """The object pickled in `path` (after the state's first line, with `header`)."""
    try:
        with path.open("rb") as f:
            if header and not f.readline(200).startswith(STATE_HEADER.encode()):
                raise ResultsError(f"{path}: not a readable checkpoint (no state header)")
            return _Unpickler(f, shared).load()
    except ResultsError:
        raise
    except OSError as exc:
        raise ResultsError(f"{path}: cannot read the checkpoint: {exc.strerror}") from None
    except Exception as exc:  # a truncated or foreign file: pickle raises many kinds of errors
        raise ResultsError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None


def _write_atomically(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """`write` streams the pickle into the file: never whole in memory (pickling to bytes held
    the state twice at each save, and left the heap as large)."""
    try:
        write_atomically(path, write)
    except OSError as exc:
        raise WriteFailed(f"{path}: cannot write the checkpoint: {exc.strerror}") from None
