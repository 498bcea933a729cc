"""Numbers a run keeps for the whole traverse but reads only at its end (a configuration's
per-stop results, the views of its landmarks, the tracks made landmarks), kept in files mapped
read-only rather than in memory, so that a run's memory does not grow with the distance driven.

Each file is unlinked as soon as it is mapped (where the system allows it): its pages stay on
disk while the array lives, and nothing is left behind when the process ends, however it ends.
Where files cannot be unlinked while mapped, they stay in the process's temporary folder, which
the next run removes (scratch.sweep)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator

import numpy as np

from ..errors import WriteFailed
from .processes import map_npy
from .scratch import PREFIX, temporary_folder

# values a file; the environment may set it (tests). The latest values wait in memory until a
# file's worth has gathered.
CHUNK = int(os.environ.get("PANCAM_GRAPH_SPILL_CHUNK", "4096"))

_folder: tempfile.TemporaryDirectory | None = None  # where files are not unlinked while mapped
_folder_pid: int | None = None


def mapped(values: np.ndarray) -> np.ndarray:
    """A read-only copy of `values` in a file, mapped (its pages released with the other mapped
    inputs: processes.release_mapped_pages)."""
    where = None if os.name == "posix" else _process_folder()
    try:
        handle, name = tempfile.mkstemp(prefix=f"{PREFIX}spill-", suffix=".npy", dir=where)
        with os.fdopen(handle, "wb") as f:
            np.save(f, np.ascontiguousarray(values))
        out = map_npy(name)
        if where is None:
            os.unlink(name)
    except OSError as exc:
        raise WriteFailed(f"{where or tempfile.gettempdir()}: cannot write a run's numbers to a temporary file: "
                          f"{exc.strerror}") from None
    return out


def _process_folder() -> str:
    global _folder, _folder_pid
    if _folder is None or _folder_pid != os.getpid():  # a forked process makes its own
        _folder, _folder_pid = temporary_folder("spill"), os.getpid()
    return _folder.name


class Column:
    """Numbers of one type (a numpy type code: "d", "q") appended one at a time over a traverse:
    the latest in memory, each `CHUNK` before them in a file (`mapped`). Read back by index, in
    order, or all at once."""

    def __init__(self, typecode: str, values: Iterable = ()) -> None:
        self._dtype = np.dtype(typecode)
        self._chunk = CHUNK
        self._files: list[np.ndarray] = []
        # one block, filled and written out again and again: no growing and shrinking in the heap
        self._tail = np.empty(self._chunk, self._dtype)
        self._n = 0  # values in it
        self.extend(values)

    def append(self, value) -> None:
        self._tail[self._n] = value
        self._n += 1
        if self._n == self._chunk:
            self._spill()

    def extend(self, values: Iterable) -> None:
        values = values if isinstance(values, np.ndarray) else np.fromiter(values, self._dtype)
        at = 0
        while at < len(values):
            take = min(self._chunk - self._n, len(values) - at)
            self._tail[self._n:self._n + take] = values[at:at + take]
            self._n, at = self._n + take, at + take
            if self._n == self._chunk:
                self._spill()

    def _spill(self) -> None:
        self._files.append(mapped(self._tail))
        self._n = 0

    def __len__(self) -> int:
        return len(self._files) * self._chunk + self._n

    def __getitem__(self, i: int):
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"index {i} out of a column of {n}")
        file, at = divmod(i % n, self._chunk)
        return (self._files[file] if file < len(self._files) else self._tail)[at].item()

    def __iter__(self) -> Iterator:
        for values in self._files:
            yield from values.tolist()
        yield from self._tail[:self._n].tolist()

    def to_numpy(self) -> np.ndarray:
        """All the values, a new array."""
        return np.concatenate([*self._files, self._tail[:self._n]])

    def __getstate__(self) -> dict:
        return {"typecode": self._dtype.char, "values": self.to_numpy()}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["typecode"], state["values"])
