"""Real GPS logs through the readers, pyproj and the GIS writers."""

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.formats.export import (
    write_geojson,
    write_kitti,
    write_kml,
    write_trajectory_exports,
)
from pancam_graph.formats.gps_logs import read_gps_csv, read_kfgins
from pancam_graph.geometry.geodesy import LocalFrame

pytestmark = pytest.mark.real_data


def read_geojson_line(path: Path) -> np.ndarray:
    """(N, 3) latitude, longitude, height of a written track's LineString, read with plain json."""
    doc = json.loads(path.read_text(encoding="utf-8"))
    features = doc["features"] if doc["type"] == "FeatureCollection" else [doc]
    line = next(f["geometry"] for f in features if f["geometry"]["type"] == "LineString")
    return np.array(line["coordinates"], dtype=float)[:, [1, 0, 2]]

REAL = Path(__file__).parents[1] / "data" / "real"
KFGINS = REAL / "kfgins" / "GNSS-RTK.txt"


def test_kfgins_round_trip_below_a_millimetre_and_geojson_rereads(tmp_path):
    fixes = read_kfgins(KFGINS)
    assert len(fixes) == 3413
    llh = np.array([[f.lat_deg, f.lon_deg, f.h_m] for f in fixes])
    origin = LocalFrame(*llh[0])
    enu = origin.to_enu(llh[:, 0], llh[:, 1], llh[:, 2])
    assert fixes[-1].time_s - fixes[0].time_s == 3412.0  # 1 Hz, 57 min, no gaps
    # (the data README says "about 28 km"; the fixes themselves trace 19.3 km)
    back = origin.to_geodetic(enu)
    metres_per_deg = 111_320.0
    horizontal = np.hypot((back[:, 0] - llh[:, 0]) * metres_per_deg,
                          (back[:, 1] - llh[:, 1]) * metres_per_deg * np.cos(np.deg2rad(llh[:, 0])))
    assert horizontal.max() < 1e-3 and np.abs(back[:, 2] - llh[:, 2]).max() < 1e-3
    path = tmp_path / "track.geojson"
    write_geojson(path, back, "kfgins")
    np.testing.assert_allclose(read_geojson_line(path), llh, atol=1e-9)  # 1e-9 deg ~ 0.1 mm


def test_kml_and_kitti_writers(tmp_path):
    llh = np.array([[30.1, 114.2, 21.5], [30.2, 114.3, 22.5]])
    write_kml(tmp_path / "t.kml", llh, "t")
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    text = ET.parse(tmp_path / "t.kml").find(".//k:LineString/k:coordinates", ns).text
    np.testing.assert_allclose([[float(v) for v in c.split(",")] for c in text.split()], llh[:, [1, 0, 2]])
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, 3] = [1.0, 2.0, 3.0]
    write_kitti(tmp_path / "t.kitti", poses)
    rows = np.loadtxt(tmp_path / "t.kitti")
    np.testing.assert_allclose(rows[1].reshape(3, 4), poses[1, :3])


def test_csv_reader_names_file_line_and_column(tmp_path):
    good = tmp_path / "fixes.csv"
    good.write_text("time_s,lat_deg,lon_deg,h_m,sigma_h_m,sigma_v_m\n0,39.7,-105.1,1700,2,3\n1,39.7001,-105.1,1700,2,3\n")
    assert [f.lat_deg for f in read_gps_csv(good)] == [39.7, 39.7001]
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,lat_deg,lon_deg,h_m\n0,39.7,-105.1,1700\n1,north,-105.1,1700\n")
    with pytest.raises(InputError, match=r"bad.csv: line 3: column 'lat_deg': expected a number, got 'north'"):
        read_gps_csv(bad, sigma_horizontal_m=2.0, sigma_vertical_m=3.0)
    with pytest.raises(InputError, match="bad.csv: line 2: no sigma columns"):
        read_gps_csv(bad)
    nohead = tmp_path / "nohead.csv"
    nohead.write_text("0,39.7,-105.1,1700\n")
    with pytest.raises(InputError, match="nohead.csv: line 1: header lacks column"):
        read_gps_csv(nohead)


def test_trajectory_exports_go_back_to_wgs84(tmp_path):
    origin = LocalFrame(39.7392, -105.1450, 1705.0)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0.0, 0.0, 0.0], [100.0, 0.0, 1.0], [100.0, 200.0, 2.0]]
    write_trajectory_exports(tmp_path, "est", origin, np.array([0.0, 1.0, 2.0]), poses)
    assert {p.name for p in tmp_path.iterdir()} == {"est.kitti", "est_wgs84.csv", "est.geojson", "est.kml"}
    llh = read_geojson_line(tmp_path / "est.geojson")
    np.testing.assert_allclose(origin.to_enu(llh[:, 0], llh[:, 1], llh[:, 2]), poses[:, :3, 3], atol=1e-3)
    assert llh[1, 1] > -105.1450 and llh[2, 0] > 39.7392  # east is +longitude, north is +latitude
