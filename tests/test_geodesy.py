import numpy as np
import pytest

from pancam_graph.errors import GeodesyError
from pancam_graph.geodesy import LocalFrame

A = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)


def _ecef(lat_deg, lon_deg, h):
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = A / np.sqrt(1.0 - E2 * np.sin(lat) ** 2)
    return np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - E2) + h) * np.sin(lat)])


def _enu_by_hand(lat0, lon0, h0, lat, lon, h):
    """Independent computation: ECEF difference rotated into the local tangent frame."""
    d = _ecef(lat, lon, h) - _ecef(lat0, lon0, h0)
    la, lo = np.radians(lat0), np.radians(lon0)
    rot = np.array([
        [-np.sin(lo), np.cos(lo), 0.0],
        [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
        [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
    ])
    return rot @ d


def test_enu_matches_independent_ecef_computation():
    frame = LocalFrame(39.7392, -105.1450, 1705.0)
    point = (39.7410, -105.1501, 1721.5)
    expected = _enu_by_hand(39.7392, -105.1450, 1705.0, *point)
    np.testing.assert_allclose(frame.to_enu(*point)[0], expected, atol=1e-4)
    assert expected[0] < 0 and expected[1] > 0  # west and north of the origin


def test_round_trip_below_a_millimetre():
    frame = LocalFrame(39.7392, -105.1450, 1705.0)
    rng = np.random.default_rng(1)
    enu = rng.uniform([-20000, -20000, -200], [20000, 20000, 800], size=(500, 3))
    back = frame.to_enu(*frame.to_geodetic(enu).T)
    assert np.abs(back - enu).max() < 1e-3


def test_bad_input_raises_typed_errors():
    frame = LocalFrame(0.0, 0.0, 0.0)
    with pytest.raises(GeodesyError, match="non-finite"):
        frame.to_enu(np.nan, 0.0, 0.0)
    with pytest.raises(GeodesyError, match="latitude"):
        frame.to_enu(91.0, 0.0, 0.0)
    with pytest.raises(GeodesyError):
        LocalFrame(95.0, 0.0, 0.0)


def test_numpy_scalar_origin_is_the_same_frame():
    lat, lon, h = np.array([49.015003823272, 8.4342971002335, 116.43032836914])
    frame = LocalFrame(lat, lon, h)  # numpy scalars, as they come out of a loaded table
    np.testing.assert_allclose(frame.to_enu(lat, lon, h), [[0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(frame.to_enu(lat + 1e-3, lon, h), LocalFrame(float(lat), float(lon), float(h))
                               .to_enu(lat + 1e-3, lon, h), atol=1e-9)
