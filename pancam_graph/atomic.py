"""Files written whole or not at all: into a temporary file beside, then renamed over the name.
A reader never sees half a file, whatever stops the writer."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def write_atomically(path: Path, write: Callable[[BinaryIO], None], durable: bool = True) -> None:
    """`write(file)` into `path`'s temporary, then the rename; `durable`: on disk before the
    rename (fsync), so a power cut leaves the old file or the new one. An OSError leaves no
    temporary behind and is the caller's to name."""
    temporary = path.with_name(path.name + ".tmp")
    try:
        with temporary.open("wb") as f:
            write(f)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(temporary, path)
    except OSError:
        temporary.unlink(missing_ok=True)
        raise
