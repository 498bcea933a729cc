"""The one way text files are read: UTF-8 with an optional byte-order mark (editors and
spreadsheets write one), and a file that cannot be read or is not UTF-8 is one message naming it."""

from __future__ import annotations

from pathlib import Path

from .errors import InputError, PancamGraphError


def read_text(path: Path, what: str = "file", error: type[PancamGraphError] = InputError) -> str:
    """The whole file as text; newlines (LF or CRLF) are left to the caller's splitting."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start:exc.start + 4]
        raise error(f"{path}: not UTF-8 text (byte {exc.start}: {bad!r})") from None
