"""The one way text files are read: UTF-8 with an optional byte-order mark (editors and
spreadsheets write one), gzipped when the name ends in .gz; a file that cannot be read or is
not UTF-8 is one message naming it."""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path

from ..errors import InputError, PancamGraphError


def read_text(path: Path, what: str = "file", error: type[PancamGraphError] = InputError) -> str:
    """The whole file as text; newlines (LF or CRLF) are left to the caller's splitting."""
    path = Path(path)
    try:
        if path.suffix == ".gz":
            return gzip.decompress(path.read_bytes()).decode("utf-8-sig")
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    except (EOFError, zlib.error) as exc:
        raise error(f"{path}: not a whole gzip file ({exc})") from None
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start:exc.start + 4]
        raise error(f"{path}: not UTF-8 text (byte {exc.start}: {bad!r})") from None
