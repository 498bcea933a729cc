"""Files written whole or not at all: into a temporary file beside, then renamed over the name.
A reader never sees half a file, whatever stops the writer. And a write that fails as one
error naming what it could not write."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

from ..errors import WriteFailed


def write_atomically(path: Path, write: Callable[[BinaryIO], None], durable: bool = True) -> None:
    """`write(file)` into `path`'s temporary, then the rename; `durable`: on disk before the
    rename (fsync), so a power cut leaves the old file or the new one. A failure (an OSError,
    which is the caller's to name, or Ctrl-C mid-write) leaves no temporary behind."""
    temporary = path.with_name(path.name + ".tmp")
    try:
        with temporary.open("wb") as f:
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@contextmanager
def writing(where: Path, what: str, discard: bool = False) -> Iterator[None]:
    """Files written inside: an OSError (a full disk, a permission) becomes one WriteFailed
    naming the file, or `where` when the system does not say which file (a failed write()).
    `discard`: `where` is a folder this write makes, removed again on failure (no half folder)."""
    try:
        yield
    except OSError as exc:
        if discard:
            shutil.rmtree(where, ignore_errors=True)
        raise WriteFailed(f"{exc.filename or where}: cannot write {what}: {exc.strerror or exc}") from None
