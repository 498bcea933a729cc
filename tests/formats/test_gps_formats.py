"""NMEA and GPX readers: real KF-GINS fixes written in those formats read back, and every bad
record named by file and line (or track point)."""

import datetime as dt
from pathlib import Path

import gpxpy
import gpxpy.gpx
import numpy as np
import pynmea2
import pytest

from pancam_graph.errors import InputError
from pancam_graph.formats.gps_logs import read_gps_file, read_gpx, read_kfgins, read_nmea

pytestmark = pytest.mark.real_data

KFGINS = Path(__file__).parents[1] / "data" / "real" / "kfgins" / "GNSS-RTK.txt"
GPS_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.UTC)
WEEK = 2100  # the KF-GINS file carries seconds of week only; any week serves a format test
GEOID_SEP_M = 12.3


def _dm(value: float, width: int) -> str:
    deg = int(abs(value))
    return f"{deg:0{width}d}{(abs(value) - deg) * 60:010.7f}"


def _nmea_lines(fixes, date: dt.date) -> list[str]:
    lines = []
    for f in fixes:
        t = (GPS_EPOCH + dt.timedelta(weeks=WEEK, seconds=f.time_s)).strftime("%H%M%S.%f")[:9]
        lat, lon = _dm(f.lat_deg, 2), _dm(f.lon_deg, 3)
        ns, ew = ("N" if f.lat_deg >= 0 else "S"), ("E" if f.lon_deg >= 0 else "W")
        lines.append(str(pynmea2.RMC("GP", "RMC", (t, "A", lat, ns, lon, ew, "0.0", "0.0", date.strftime("%d%m%y"),
                                                    "", ""))))
        lines.append(str(pynmea2.GGA("GP", "GGA", (t, lat, ns, lon, ew, "4", "12", "0.8",
                                                    f"{f.h_m - GEOID_SEP_M:.4f}", "M", f"{GEOID_SEP_M}", "M", "", ""))))
        lines.append(str(pynmea2.GST("GP", "GST", (t, "0.5", "", "", "", "0.03", "0.04", "0.05"))))
    return lines


def test_nmea_of_real_fixes_reads_back_with_ellipsoidal_height_and_stated_sigma(tmp_path):
    fixes = read_kfgins(KFGINS)[:300]
    date = (GPS_EPOCH + dt.timedelta(weeks=WEEK, seconds=fixes[0].time_s)).date()
    path = tmp_path / "drive.nmea"
    path.write_text("\n".join(_nmea_lines(fixes, date)) + "\n")
    got, rejected = read_nmea(path)
    assert rejected == [] and len(got) == len(fixes)
    lat = np.array([[g.lat_deg, g.lon_deg, g.h_m] for g in got])
    ref = np.array([[f.lat_deg, f.lon_deg, f.h_m] for f in fixes])
    np.testing.assert_allclose(lat[:, :2], ref[:, :2], atol=2e-9)  # 7 decimals of minutes: < 0.2 mm
    np.testing.assert_allclose(lat[:, 2], ref[:, 2], atol=1e-4)  # altitude + geoid separation
    # UTC time from RMC date + GGA time of day; GPS time runs 18 s ahead of UTC, not corrected here.
    expected = np.array([(GPS_EPOCH + dt.timedelta(weeks=WEEK, seconds=f.time_s)).timestamp() for f in fixes])
    np.testing.assert_allclose([g.time_s for g in got], np.floor(expected * 100) / 100, atol=1e-6)
    assert got[0].sigma_horizontal_m == pytest.approx(np.sqrt(0.5 * (0.03**2 + 0.04**2)))
    assert got[0].sigma_vertical_m == 0.05
    assert read_gps_file(path)[0] == got


def test_nmea_rejects_bad_checksum_and_no_fix_with_line_numbers(tmp_path):
    good = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"
    bad_checksum = good[:-2] + "48"
    no_fix = str(pynmea2.GGA("GP", "GGA", ("123520", "", "", "", "", "0", "00", "", "", "M", "", "M", "", "")))
    no_checksum = good.split("*")[0]
    rmc = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"
    path = tmp_path / "log.nmea"
    path.write_text("\n".join([rmc, good, bad_checksum, no_fix, no_checksum, "$GPGGA,garbage*00"]) + "\n")
    fixes, rejected = read_nmea(path, sigma_horizontal_m=2.0, sigma_vertical_m=4.0)
    assert len(fixes) == 1
    f = fixes[0]
    assert (f.lat_deg, f.lon_deg) == pytest.approx((48.1173, 11.516666666667))
    assert f.h_m == pytest.approx(545.4 + 46.9)
    assert f.time_s == dt.datetime(1994, 3, 23, 12, 35, 19, tzinfo=dt.UTC).timestamp()
    assert (f.sigma_horizontal_m, f.sigma_vertical_m) == (2.0, 4.0)  # no GST: configured
    assert len(rejected) == 4
    assert rejected[0].startswith(f"{path}: line 3: checksum does not match")
    assert rejected[1] == f"{path}: line 4: GGA without a fix (quality 0)"
    assert rejected[2].startswith(f"{path}: line 5: strict checking requested but checksum missing")
    assert rejected[3].startswith(f"{path}: line 6: ")


def test_nmea_without_rmc_or_sigma_is_an_error(tmp_path):
    path = tmp_path / "gga_only.nmea"
    path.write_text("$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\n")
    with pytest.raises(InputError, match="no RMC sentence with a date"):
        read_nmea(path, 1.0, 1.0)
    path.write_text(path.read_text() + "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A\n")
    with pytest.raises(InputError, match=r"line 1: no GST sentence for this fix and no sigma configured"):
        read_nmea(path)


def _gpx(points) -> str:
    gpx = gpxpy.gpx.GPX()
    track = gpxpy.gpx.GPXTrack()
    segment = gpxpy.gpx.GPXTrackSegment()
    gpx.tracks.append(track)
    track.segments.append(segment)
    segment.points.extend(points)
    return gpx.to_xml()


def test_gpx_of_real_fixes_reads_back(tmp_path):
    fixes = read_kfgins(KFGINS)[:100]
    t0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)
    points = [gpxpy.gpx.GPXTrackPoint(f.lat_deg, f.lon_deg, elevation=f.h_m - GEOID_SEP_M,
                                      time=t0 + dt.timedelta(seconds=f.time_s - fixes[0].time_s)) for f in fixes]
    path = tmp_path / "drive.gpx"
    path.write_text(_gpx(points))
    got = read_gpx(path, 1.5, 3.0, geoid_separation_m=GEOID_SEP_M)
    np.testing.assert_allclose([[g.lat_deg, g.lon_deg, g.h_m] for g in got],
                               [[f.lat_deg, f.lon_deg, f.h_m] for f in fixes], atol=1e-9)
    assert got[5].time_s - got[0].time_s == pytest.approx(fixes[5].time_s - fixes[0].time_s)
    assert got[0].sigma_horizontal_m == 1.5


def test_gpx_point_without_elevation_is_named(tmp_path):
    t0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)
    points = [gpxpy.gpx.GPXTrackPoint(30.0, 114.0, elevation=20.0, time=t0),
              gpxpy.gpx.GPXTrackPoint(30.0001, 114.0, elevation=None, time=t0 + dt.timedelta(seconds=1))]
    path = tmp_path / "no_ele.gpx"
    path.write_text(_gpx(points))
    with pytest.raises(InputError, match=r"no_ele.gpx: track 0, segment 0, point 1 \(30.0001, 114.0\): no <ele>"):
        read_gpx(path, 1.0, 2.0)


def test_gpx_point_off_the_globe_is_named(tmp_path):
    t0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)
    points = [gpxpy.gpx.GPXTrackPoint(30.0, 114.0, elevation=20.0, time=t0),
              gpxpy.gpx.GPXTrackPoint(95.0, 114.0, elevation=20.0, time=t0 + dt.timedelta(seconds=1))]
    path = tmp_path / "north.gpx"
    path.write_text(_gpx(points))
    with pytest.raises(InputError, match=r"north.gpx: track 0, segment 0, point 1 \(95.0, 114.0\): latitude or "
                                         r"longitude out of range"):
        read_gpx(path, 1.0, 2.0)


def test_a_byte_order_mark_and_crlf_read_the_same_and_other_bytes_are_named(tmp_path):
    """What Windows tools and spreadsheets write (issue 15): NMEA, GPX, KF-GINS and GPS CSV."""
    fixes = read_kfgins(KFGINS)[:50]
    date = (GPS_EPOCH + dt.timedelta(weeks=WEEK, seconds=fixes[0].time_s)).date()
    t0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)
    points = [gpxpy.gpx.GPXTrackPoint(f.lat_deg, f.lon_deg, elevation=f.h_m,
                                      time=t0 + dt.timedelta(seconds=f.time_s - fixes[0].time_s)) for f in fixes]
    csv_text = "time_s,lat_deg,lon_deg,h_m,sigma_h_m,sigma_v_m\n" + "".join(
        f"{f.time_s},{f.lat_deg!r},{f.lon_deg!r},{f.h_m},1.0,2.0\n" for f in fixes)
    files = {"drive.nmea": "\n".join(_nmea_lines(fixes, date)) + "\n", "drive.gpx": _gpx(points),
             "drive.txt": "".join(KFGINS.read_text().splitlines(keepends=True)[:50]), "drive.csv": csv_text}

    def read(path):
        if path.suffix == ".gpx":
            return read_gpx(path, 1.5, 3.0)
        if path.suffix == ".txt":
            return read_kfgins(path)
        return read_gps_file(path)

    for name, text in files.items():
        plain, windows = tmp_path / name, tmp_path / f"windows_{name}"
        plain.write_text(text)
        windows.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
        assert read(windows) == read(plain) and len(read(plain)) > 0, name
        broken = tmp_path / f"latin1_{name}"
        broken.write_bytes(text.encode()[:200] + b"\xe9\xff" + text.encode()[200:])
        with pytest.raises(InputError, match=rf"latin1_{name}: not UTF-8 text \(byte 200"):
            read(broken)
