"""GPS logs as fixes: NMEA 0183, GPX, tables with declared columns (CSV with a header, KF-GINS text).

Every rejected line or bad value is named by file and line. Heights are ellipsoidal (WGS84)
unless the file says otherwise; sigmas are 1 sigma in metres, horizontal per axis.
"""

from __future__ import annotations

import bisect
import csv
import datetime as dt
import io
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..records import GpsFix
from ..runtime.text_files import read_text

# The CSV columns this reader understands; time, latitude, longitude and height are required.
MAX_SIGMA_M = 1e4  # a fix less certain than this says nothing (and squares past float range)
CSV_REQUIRED = ("time_s", "lat_deg", "lon_deg", "h_m")
# KF-GINS GNSS files: GPS seconds of week, lat, lon, ellipsoidal height, std north, east, up.
KFGINS_COLUMNS = ("time_s", "lat_deg", "lon_deg", "h_m", "sigma_n_m", "sigma_e_m", "sigma_u_m")


def read_gps_csv(path: Path, sigma_horizontal_m: float | None = None, sigma_vertical_m: float | None = None
                 ) -> list[GpsFix]:
    """CSV with a header naming at least time_s, lat_deg, lon_deg, h_m (ellipsoidal; or
    h_ellipsoidal_m, as the results folder's trajectories name it), and optionally
    sigma_h_m / sigma_v_m or sigma_n_m / sigma_e_m / sigma_u_m; missing sigmas take the
    configured ones."""
    path = Path(path)
    with _open(path) as f:
        reader = csv.DictReader(f)
        try:
            header = reader.fieldnames or []
            if "h_m" not in header and "h_ellipsoidal_m" in header:  # our own *_wgs84.csv trajectories
                reader.fieldnames = header = ["h_m" if c == "h_ellipsoidal_m" else c for c in header]
            missing = [c for c in CSV_REQUIRED if c not in header]
            if missing:
                raise InputError(f"{path}: line 1: header lacks column(s) {', '.join(missing)} "
                                 f"(has {', '.join(header) or 'nothing'})")
            rows = [(reader.line_num, row) for row in reader]
        except csv.Error as exc:  # e.g. a field over the csv module's 131,072 characters
            raise InputError(f"{path}: line {reader.line_num}: not a CSV row this reader takes ({exc})") from None
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


def _open(path: Path) -> io.StringIO:
    return io.StringIO(read_text(path, "GPS file"), newline="")


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
        sigma_h = float(np.hypot(number("sigma_n_m"), number("sigma_e_m")) / np.sqrt(2.0))
    if row.get("sigma_v_m") not in (None, ""):
        sigma_v = number("sigma_v_m")
    elif row.get("sigma_u_m") not in (None, ""):
        sigma_v = number("sigma_u_m")
    if sigma_h is None or sigma_v is None:
        raise InputError(f"{path}: line {line}: no sigma columns and no sigma configured")
    if not (0 < sigma_h <= MAX_SIGMA_M and 0 < sigma_v <= MAX_SIGMA_M):
        raise InputError(f"{path}: line {line}: sigmas {sigma_h:.3g}, {sigma_v:.3g} m must be in (0, {MAX_SIGMA_M:g}]")
    return GpsFix(number("time_s"), lat, lon, number("h_m"), sigma_h, sigma_v)


# -- NMEA 0183 ---------------------------------------------------------------------------------

def read_nmea(path: Path, sigma_horizontal_m: float | None = None, sigma_vertical_m: float | None = None
              ) -> tuple[list[GpsFix], list[str]]:
    """GGA fixes of an NMEA 0183 log, and the reason for every sentence left out.

    - Time: GGA carries the time of day only; the date comes from the latest RMC sentence
      (the first one in the file for fixes logged before it). `time_s` is UTC Unix time.
    - Height: ellipsoidal = GGA altitude (above the geoid) + geoid separation.
    - Sigma: the GST sentence of the same epoch when the receiver writes one (stated),
      otherwise the configured sigmas.
    - Rejected with a reason naming the line: bad or missing checksum, unparsable sentence,
      no fix (GGA quality 0: such sentences read as latitude = longitude = 0).
    """
    import pynmea2

    path = Path(path)
    rejected: list[tuple[int, str]] = []
    gga: list[tuple[int, pynmea2.GGA]] = []
    rmc: list[tuple[int, pynmea2.RMC]] = []
    gst: dict[object, pynmea2.GST] = {}
    with _open(path) as f:
        for line, text in enumerate(f, start=1):
            text = text.strip()
            if not text.startswith(("$", "!")):
                continue
            try:
                msg = pynmea2.parse(text, check=True)
            except pynmea2.ChecksumError as exc:
                rejected.append((line, f"{path}: line {line}: {_reason(exc)}"))
                continue
            except (pynmea2.ParseError, ValueError) as exc:
                rejected.append((line, f"{path}: line {line}: unparsable sentence: {_reason(exc)}"))
                continue
            try:  # pynmea2 parses fields when they are first read
                if isinstance(msg, pynmea2.GGA):
                    gga.append((line, msg))
                elif (isinstance(msg, pynmea2.RMC) and isinstance(msg.datestamp, dt.date)
                      and isinstance(msg.timestamp, dt.time)):
                    rmc.append((line, msg))
                elif isinstance(msg, pynmea2.GST) and isinstance(msg.timestamp, dt.time):
                    gst[msg.timestamp] = msg
            except (ValueError, TypeError) as exc:
                rejected.append((line, f"{path}: line {line}: unparsable sentence: {_reason(exc)}"))
    if gga and not rmc:
        raise InputError(f"{path}: {len(gga)} GGA sentences but no RMC sentence with a date; "
                         "GGA carries only the time of day")

    fixes = []
    for line, msg in gga:
        try:
            fix = _gga_fix(path, line, msg, gst, rmc, sigma_horizontal_m, sigma_vertical_m)
        except (ValueError, TypeError, OverflowError) as exc:  # a field pynmea2 parses only when read
            fix = f"{path}: line {line}: unparsable GGA: {_reason(exc)}"
        if isinstance(fix, str):
            rejected.append((line, fix))
        else:
            fixes.append(fix)
    return fixes, [reason for _, reason in sorted(rejected)]


def _gga_fix(path: Path, line: int, msg, gst: dict, rmc: list, sigma_horizontal_m: float | None,
             sigma_vertical_m: float | None) -> GpsFix | str:
    """The fix of a GGA sentence, or why it is rejected."""
    where = f"{path}: line {line}"
    if not msg.gps_qual:
        return f"{where}: GGA without a fix (quality {msg.gps_qual or 0})"
    if not isinstance(msg.timestamp, dt.time) or msg.altitude is None or not msg.lat or not msg.lon:
        return f"{where}: GGA lacks time, position or altitude"
    try:
        separation = float(msg.geo_sep) if msg.geo_sep else 0.0
    except ValueError:
        return f"{where}: geoid separation {msg.geo_sep!r} is not a number"
    stated = gst.get(msg.timestamp)
    sigma_h, sigma_v = sigma_horizontal_m, sigma_vertical_m
    if stated is not None and stated.std_dev_latitude and stated.std_dev_longitude:
        sigma_h = float(np.hypot(float(stated.std_dev_latitude), float(stated.std_dev_longitude)) / np.sqrt(2.0))
        if stated.std_dev_altitude:
            sigma_v = float(stated.std_dev_altitude)
    if sigma_h is None or sigma_v is None:
        raise InputError(f"{where}: no GST sentence for this fix and no sigma configured")
    lat, lon, h = float(msg.latitude), float(msg.longitude), float(msg.altitude) + separation
    if not (np.isfinite([lat, lon, h]).all() and -90 <= lat <= 90 and -180 <= lon <= 180):
        return f"{where}: position {lat}, {lon}, {h} is not on the Earth"
    if not (0 < sigma_h <= MAX_SIGMA_M and 0 < sigma_v <= MAX_SIGMA_M):
        return f"{where}: GST sigmas {sigma_h:.3g}, {sigma_v:.3g} m are not in (0, {MAX_SIGMA_M:g}]"
    return GpsFix(_utc_seconds(line, msg.timestamp, rmc), lat, lon, h, sigma_h, sigma_v)


def _reason(exc: Exception) -> str:
    # pynmea2 puts (message, fields) in args[0]
    first = exc.args[0] if exc.args else exc
    return str(first[0] if isinstance(first, tuple) else first)


def _utc_seconds(line: int, time_of_day, rmc: list) -> float:
    """UTC Unix time of a GGA time of day, dated by the latest RMC at or before `line`."""
    # rmc is in file order: the latest one at or before `line` (else the first one)
    i = bisect.bisect_right(rmc, line, key=lambda entry: entry[0])
    date_msg = rmc[max(i - 1, 0)][1]
    stamp = dt.datetime.combine(date_msg.datestamp, time_of_day)
    # The GGA may already belong to the next day while the last RMC is from before midnight.
    rmc_stamp = dt.datetime.combine(date_msg.datestamp, date_msg.timestamp)
    if (rmc_stamp - stamp).total_seconds() > 12 * 3600:
        stamp += dt.timedelta(days=1)
    elif (stamp - rmc_stamp).total_seconds() > 12 * 3600:
        stamp -= dt.timedelta(days=1)
    return stamp.timestamp()


# -- GPX ---------------------------------------------------------------------------------------

def read_gpx(path: Path, sigma_horizontal_m: float, sigma_vertical_m: float, geoid_separation_m: float = 0.0
             ) -> list[GpsFix]:
    """Track points of a GPX file. GPX states no accuracy, so the configured sigmas apply.

    GPX `ele` is, by most receivers, height above the geoid: ellipsoidal height =
    ele + `geoid_separation_m` (0 by default, i.e. `ele` is taken as ellipsoidal). A point
    without time or elevation is an error naming track, segment and point.
    """
    import gpxpy
    import gpxpy.gpx

    path = Path(path)
    with _open(path) as f:
        try:
            gpx = gpxpy.parse(f)
        except gpxpy.gpx.GPXException as exc:
            raise InputError(f"{path}: not a readable GPX file: {exc}") from None
    fixes = []
    for ti, track in enumerate(gpx.tracks):
        for si, segment in enumerate(track.segments):
            for pi, p in enumerate(segment.points):
                where = f"{path}: track {ti}, segment {si}, point {pi} ({p.latitude}, {p.longitude})"
                if p.elevation is None:
                    raise InputError(f"{where}: no <ele> elevation; a fix needs a height")
                if p.time is None:
                    raise InputError(f"{where}: no <time>")
                if not (-90.0 <= p.latitude <= 90.0 and -180.0 <= p.longitude <= 360.0):
                    raise InputError(f"{where}: latitude or longitude out of range")
                stamp = p.time if p.time.tzinfo is not None else p.time.replace(tzinfo=dt.UTC)
                fixes.append(GpsFix(stamp.timestamp(), float(p.latitude), float(p.longitude),
                                    float(p.elevation) + geoid_separation_m, sigma_horizontal_m, sigma_vertical_m))
    if not fixes:
        raise InputError(f"{path}: no track points")
    return fixes


# -- any of the above --------------------------------------------------------------------------

def read_gps_file(path: Path, sigma_horizontal_m: float | None = None, sigma_vertical_m: float | None = None
                  ) -> tuple[list[GpsFix], list[str]]:
    """Fixes of a GPS log in any format above, told apart by content (and `.gpx` by name), with
    the reasons for left-out records. Configured sigmas apply where the file states none."""
    path = Path(path)
    if path.suffix.lower() == ".gpx":
        if sigma_horizontal_m is None or sigma_vertical_m is None:
            raise InputError(f"{path}: GPX states no accuracy; configure the GPS sigmas")
        return read_gpx(path, sigma_horizontal_m, sigma_vertical_m), []
    with _open(path) as f:
        first = next((text.strip() for text in f if text.strip() and not text.startswith("#")), "")
    if first.startswith(("$", "!")):
        return read_nmea(path, sigma_horizontal_m, sigma_vertical_m)
    if "lat_deg" in first.split(","):
        return read_gps_csv(path, sigma_horizontal_m, sigma_vertical_m), []
    if len(first.split()) == len(KFGINS_COLUMNS):
        return read_kfgins(path), []
    raise InputError(f"{path}: not a GPS log this reader knows (NMEA, GPX, CSV with a lat_deg header, "
                     f"KF-GINS); first line: {first[:80]!r}")
