"""Plain table and document files (CSV with a header, JSON) as every writer here writes them."""

from __future__ import annotations

import copy
import csv
import io
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..runtime.text_files import read_text


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n", encoding="utf-8")


def write_csv(path: Path, header: list[str], rows) -> None:
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


class CsvTable:
    """Rows of a CSV file with required columns; every bad value names file, line and column."""

    def __init__(self, path: Path, columns: list[str], optional: list[str] = ()):
        self.path = path
        reader = csv.reader(io.StringIO(read_text(path), newline=""))
        try:
            header = [c.strip() for c in next(reader, [])]
            missing = [c for c in columns if c not in header]
            if missing:
                raise InputError(f"{path}: line 1: missing column(s) {', '.join(missing)} "
                                 f"(expected {','.join(columns)})")
            self.index = [header.index(c) for c in columns]
            self.optional_index = {c: header.index(c) for c in optional if c in header}
            self.columns = columns
            self.header = header
            self.rows = [(line, row) for line, row in enumerate(reader, start=2) if row]
        except csv.Error as exc:  # e.g. a field over the csv module's 131,072 characters
            raise InputError(f"{path}: line {reader.line_num}: not a CSV row this reader takes ({exc})") from None

    def where(self, keep: np.ndarray) -> CsvTable:
        """The same table with only the rows where `keep` (a boolean per row) is true."""
        subset = copy.copy(self)
        subset.rows = [r for r, k in zip(self.rows, keep.tolist(), strict=True) if k]
        return subset

    def lines(self) -> np.ndarray:
        """Each row's line in the file."""
        return np.array([line for line, _ in self.rows], dtype=np.int64)

    def check_widths(self) -> None:
        """Every row has the required columns; the first short one is named as values() names it."""
        need = max(self.index) + 1
        short = next(((line, row) for line, row in self.rows if len(row) < need), None)
        if short is not None:
            self.values(*short)

    def texts(self, column: str) -> list[str]:
        """Every row's field of `column`: a required one (after check_widths), or an optional
        one every row has."""
        i = self.index[self.columns.index(column)] if column in self.columns else self.optional_index[column]
        return [row[i] for _, row in self.rows]

    def numbers(self, column: str) -> np.ndarray:
        """Every row's `column` as a finite float, in file order (the rows' own check, number(),
        names the first bad one)."""
        return self._parsed(column, np.float64, np.isfinite, lambda line, text: self.number(line, column, text))

    def pixels(self, column: str, extent: int) -> np.ndarray:
        """Every row's `column` as a pixel coordinate along a side of `extent` px (see pixel())."""
        return self._parsed(column, np.float64, lambda v: np.isfinite(v) & (v >= -extent) & (v <= 2 * extent),
                            lambda line, text: self.pixel(line, column, text, extent))

    def stops(self, n: int) -> np.ndarray:
        """Every row's stop, each one of 0..n-1 (see stop())."""
        return self._parsed("stop", np.int64, lambda k: (k >= 0) & (k < n), lambda line, text: self.stop(line, text, n))

    def tracks(self) -> np.ndarray:
        """Every row's track (see track())."""
        return self._parsed("track", np.int64, lambda t: t >= 0, self.track)

    def integers(self, column: str, low: int, high: int, outside: str) -> np.ndarray:
        """Every row's `column` as an integer in low..high-1; one outside is refused with the
        message `outside` ({value} in it is the row's value)."""
        def one(line: int, text: str) -> int:
            value = int(self.number(line, column, text, integer=True))
            if not low <= value < high:
                raise InputError(f"{self.path}: line {line}: " + outside.format(value=value))
            return value

        return self._parsed(column, np.int64, lambda v: (v >= low) & (v < high), one)

    def _parsed(self, column: str, dtype, valid, one) -> np.ndarray:
        """The column parsed by numpy at once; where numpy refuses a text or `valid` flags a
        value, row by row with `one(line, text)`, which raises naming the first bad row (numpy
        accepts no text Python's int() and float() refuse)."""
        texts = self.texts(column)
        try:
            values = np.array(texts, dtype=dtype)
            if np.all(valid(values)):
                return values
        except (ValueError, OverflowError):
            pass
        return np.array([one(line, text) for (line, _), text in zip(self.rows, texts, strict=True)], dtype=dtype)

    def values(self, line: int, row: list[str]) -> list[str]:
        if len(row) < max(self.index) + 1:
            lacking = [c for c, i in zip(self.columns, self.index, strict=True) if i >= len(row)]
            raise InputError(f"{self.path}: line {line}: {len(row)} fields, no {', '.join(lacking)} (the header "
                             f"names {len(self.header)} columns: {','.join(self.header)})")
        return [row[i] for i in self.index]

    def number(self, line: int, column: str, text: str, integer: bool = False) -> float:
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise InputError(f"{self.path}: line {line}: column '{column}': expected {kind}, got {text!r}") from None
        if not integer and not np.isfinite(value):
            raise InputError(f"{self.path}: line {line}: column '{column}' is not finite")
        return value

    def pixel(self, line: int, column: str, text: str, extent: int) -> float:
        """A pixel coordinate along an image side of `extent` px. Tracks run a little past the
        edge; one further than an image size from it is no measurement of the image."""
        value = self.number(line, column, text)
        if not -extent <= value <= 2 * extent:
            raise InputError(f"{self.path}: line {line}: column '{column}' = {value:g} px lies more than an image "
                             f"size ({extent} px) outside the image")
        return value

    def optional_numbers(self, column: str, default: float) -> np.ndarray:
        """An optional column: `default` where the table has no such column or a row leaves it
        empty, else as numbers() reads it."""
        i = self.optional_index.get(column)
        if i is None:
            return np.full(len(self.rows), default)
        filled = np.array([i < len(row) and row[i] != "" for _, row in self.rows], dtype=bool)
        values = np.full(len(self.rows), default)
        values[filled] = self.where(filled).numbers(column)
        return values

    def stops_and_numbers(self, n: int) -> Iterator[tuple[int, int, list[float]]]:
        """(line, stop, numbers) of a table whose first column is a stop and the rest are numbers."""
        for line, row in self.rows:
            values = self.values(line, row)
            numbers = [self.number(line, c, v) for c, v in zip(self.columns[1:], values[1:], strict=True)]
            yield line, self.stop(line, values[0], n), numbers

    def track(self, line: int, text: str) -> int:
        t = int(self.number(line, "track", text, integer=True))
        if not 0 <= t < 2**63:  # an int64 in every array that holds tracks
            raise InputError(f"{self.path}: line {line}: track {t} outside 0..2^63-1")
        return t

    def stop(self, line: int, text: str, n: int) -> int:
        k = int(self.number(line, "stop", text, integer=True))
        if not 0 <= k < n:
            raise InputError(f"{self.path}: line {line}: stop {k} is not one of stereo.csv's stops 0..{n - 1}")
        return k
