"""Plain text files: every reader's way in (UTF-8, a byte-order mark allowed, other bytes and
unreadable files one message naming the file), and the tables and documents (CSV with a header,
JSON) every writer here writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from ..errors import InputError


def read_text(path: Path, what: str = "file") -> str:
    """The whole file as text; newlines (LF or CRLF) are left to the caller's splitting."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"{path}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start:exc.start + 4]
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}: {bad!r})") from None


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n", encoding="utf-8")


def write_csv(path: Path, header: list[str], rows) -> None:
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
