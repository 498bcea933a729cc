"""The localization product (formats/localization.py): its ellipse, its angles and its latitudes
against formulas written here, and the GeoPackage read back with pyogrio in the body's CRS."""

import json

import numpy as np
import pyogrio
import pytest
from pyproj import CRS
from scipy.spatial.transform import Rotation

from pancam_graph.formats.localization import COLUMNS, horizontal_ellipse, localization, write_localization
from pancam_graph.geometry.geodesy import LocalFrame

MARS_A_M, MARS_B_M = 3396190.0, 3376200.0  # IAU 2015 Mars ellipsoid (the sphere is A)


@pytest.mark.parametrize("azimuth_deg", [0.0, 30.0, 135.0])
def test_the_ellipse_has_the_covariance_s_axes_and_azimuth(azimuth_deg):
    a = np.deg2rad(azimuth_deg)
    major = np.array([np.sin(a), np.cos(a)])  # east, north of an azimuth clockwise from north
    minor = np.array([np.cos(a), -np.sin(a)])
    covariance = np.zeros((1, 3, 3))
    covariance[0, :2, :2] = 4.0 * np.outer(major, major) + 0.25 * np.outer(minor, minor)
    covariance[0, 2, 2] = 9.0
    np.testing.assert_allclose(horizontal_ellipse(covariance)[0], [2.0, 0.5, azimuth_deg, 3.0], atol=1e-9)


def _product(tmp_path):
    origin = LocalFrame(-4.5895, 137.4416, 0.0, body="mars")
    rng = np.random.default_rng(5)
    poses = np.tile(np.eye(4), (6, 1, 1))
    truth = Rotation.from_euler("ZYX", rng.uniform(-0.3, 0.3, (6, 3)))
    # a rover heading (yaw) east of north, pitched and rolled, in east-north-up with a body forward-left-up
    ned_R_frd = truth.as_matrix()
    flip_ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    poses[:, :3, :3] = flip_ned @ ned_R_frd @ np.diag([1.0, -1.0, -1.0])
    poses[:, :3, 3] = rng.uniform(-300, 300, (6, 3))
    covariance = np.tile(np.diag([0.04, 0.09, 0.01]), (6, 1, 1))
    product = localization("onboard", origin, np.arange(6.0), poses, covariance, np.array([[4, k] for k in range(6)]))
    return origin, truth, product, write_localization(tmp_path, product)


def test_the_angles_latitudes_and_map_coordinates_are_the_formulas(tmp_path):
    origin, truth, product, _ = _product(tmp_path)
    np.testing.assert_allclose(product.ypr_deg[:, 0], np.degrees(truth.as_euler("ZYX")[:, 0]) % 360, atol=1e-9)
    np.testing.assert_allclose(product.ypr_deg[:, 1:], np.degrees(truth.as_euler("ZYX")[:, 1:]), atol=1e-9)
    # planetographic from planetocentric latitude on the ellipsoid: tan(g) = (a / b)^2 tan(c) (heights of a
    # few hundred metres move it by less than 1e-4 deg here)
    centric = np.radians(product.geodetic[:, 0])
    graphic = np.degrees(np.arctan((MARS_A_M / MARS_B_M) ** 2 * np.tan(centric)))
    np.testing.assert_allclose(product.vertical_latitude, graphic, atol=1e-4)
    # equirectangular on the sphere, standard parallel at the origin's latitude
    east = MARS_A_M * np.cos(np.radians(origin.lat0_deg)) * np.radians(product.geodetic[:, 1])
    np.testing.assert_allclose(product.map_xy[:, 0], east, atol=1e-3)
    np.testing.assert_allclose(product.map_xy[:, 1], MARS_A_M * np.radians(product.geodetic[:, 0]), atol=1e-3)


def test_the_geopackage_reads_back_in_iau_2015_with_its_columns(tmp_path):
    origin, _, product, paths = _product(tmp_path)
    gpkg = next(p for p in paths if p.suffix == ".gpkg")
    assert {tuple(layer) for layer in pyogrio.list_layers(gpkg)} == {("stops", "Point Z"), ("track", "LineString Z")}
    meta, _, geometry, fields = pyogrio.raw.read(gpkg, layer="stops")
    assert CRS.from_user_input(meta["crs"]).equals(CRS.from_user_input("IAU_2015:49900"))
    assert list(meta["fields"]) == COLUMNS
    lon_lat_h = np.array([np.frombuffer(g[5:], "<f8") for g in geometry])
    np.testing.assert_allclose(lon_lat_h, product.geodetic[:, [1, 0, 2]], atol=1e-12)
    np.testing.assert_allclose(fields[COLUMNS.index("planetocentric_latitude")], product.geodetic[:, 0])
    doc = json.loads(next(p for p in paths if p.suffix == ".geojson").read_text())
    assert doc["features"][0]["geometry"]["type"] == "LineString"
    assert doc["features"][1]["properties"]["site"] == 4 and len(doc["features"]) == 7
