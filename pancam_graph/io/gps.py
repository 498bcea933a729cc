"""GPS logs as fixes: tables with declared columns (CSV with a header, KF-GINS text).

Every rejected line or bad value is named by file and line. Heights are ellipsoidal (WGS84)
unless the file says otherwise; sigmas are 1 sigma in metres, horizontal per axis.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..records import GpsFix

# The CSV columns this reader understands; time, latitude, longitude and height are required.
CSV_REQUIRED = ("time_s", "lat_deg", "lon_deg", "h_m")
# KF-GINS GNSS files: GPS seconds of week, lat, lon, ellipsoidal height, std north, east, up.
KFGINS_COLUMNS = ("time_s", "lat_deg", "lon_deg", "h_m", "sigma_n_m", "sigma_e_m", "sigma_u_m")


def read_gps_csv(path: Path, sigma_horizontal_m: float | None = None, sigma_vertical_m: float | None = None
                 ) -> list[GpsFix]:
    """CSV with a header naming at least time_s, lat_deg, lon_deg, h_m, and optionally
    sigma_h_m / sigma_v_m or sigma_n_m / sigma_e_m / sigma_u_m; missing sigmas take the
    configured ones."""
    path = Path(path)
    with _open(path) as f:
        reader = csv.DictReader(f)
        header = reader.fieldnames or []
        missing = [c for c in CSV_REQUIRED if c not in header]
        if missing:
            raise InputError(f"{path}: line 1: header lacks column(s) {', '.join(missing)} "
                             f"(has {', '.join(header) or 'nothing'})")
        rows = [(reader.line_num, row) for row in reader]
    return [_fix(path, line, row, sigma_horizontal_m, sigma_vertical_m) for line, row in rows]


def read_kfgins(path: Path) -> list[GpsFix]:
    """A KF-GINS GNSS text file (whitespace separated, no header)."""
    path = Path(path)
    fixes = []
    with _open(path) as f:
        for line, text in enumerate(f, start=1):
            fields = text.split()
            if not fields or fields[0].startswith("#"):
                continue
            if len(fields) != len(KFGINS_COLUMNS):
                raise InputError(f"{path}: line {line}: expected {len(KFGINS_COLUMNS)} columns "
                                 f"({' '.join(KFGINS_COLUMNS)}), got {len(fields)}")
            fixes.append(_fix(path, line, dict(zip(KFGINS_COLUMNS, fields, strict=True)), None, None))
    return fixes


def _open(path: Path):
    try:
        return path.open(encoding="utf-8", newline="")
    except OSError as exc:
        raise InputError(f"{path}: cannot open: {exc.strerror}") from None


def _fix(path: Path, line: int, row: dict, sigma_h: float | None, sigma_v: float | None) -> GpsFix:
    def number(column: str) -> float:
        try:
            value = float(row[column])
        except (TypeError, ValueError):
            raise InputError(f"{path}: line {line}: column '{column}': expected a number, "
                             f"got {row[column]!r}") from None
        if not np.isfinite(value):
            raise InputError(f"{path}: line {line}: column '{column}' is not finite")
        return value

    lat, lon = number("lat_deg"), number("lon_deg")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise InputError(f"{path}: line {line}: latitude {lat} / longitude {lon} out of range")
    if row.get("sigma_h_m") not in (None, ""):
        sigma_h = number("sigma_h_m")
    elif row.get("sigma_n_m") not in (None, "") and row.get("sigma_e_m") not in (None, ""):
        sigma_h = float(np.sqrt(0.5 * (number("sigma_n_m") ** 2 + number("sigma_e_m") ** 2)))
    if row.get("sigma_v_m") not in (None, ""):
        sigma_v = number("sigma_v_m")
    elif row.get("sigma_u_m") not in (None, ""):
        sigma_v = number("sigma_u_m")
    if sigma_h is None or sigma_v is None:
        raise InputError(f"{path}: line {line}: no sigma columns and no sigma configured")
    if sigma_h <= 0 or sigma_v <= 0:
        raise InputError(f"{path}: line {line}: sigmas must be positive")
    return GpsFix(number("time_s"), lat, lon, number("h_m"), sigma_h, sigma_v)
