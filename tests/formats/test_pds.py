"""PDS3 rover image labels (formats/pds.py) read from the real Curiosity Navcam products: times,
motion counters, the onboard poses chained through the site frames and turned into east-north-up,
checked against MSLICE's ground-updated positions (an independent reference: 2.1 m median over
site 4, a 0.27 deg rotation and a 0.27 % scale, as the data's README states); bad labels named."""

from pathlib import Path

import numpy as np
import pytest
from mars_reference import mslice_locations

from pancam_graph.errors import InputError
from pancam_graph.formats.pds import enu_T_body, read_pds3_label, read_rover_images, site_origins
from pancam_graph.geometry.geodesy import LocalFrame

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
CURIOSITY = REAL / "curiosity_navcam_sol26_57"
pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(not CURIOSITY.is_dir(), reason=f"needs {CURIOSITY} (../shared beside the checkout)")]


@pytest.fixture(scope="module")
def images():
    return read_rover_images(CURIOSITY)


def test_every_label_reads_with_its_time_counter_pose_and_camera(images):
    assert len(images) == 122
    assert [i.utc_s for i in images] == sorted(i.utc_s for i in images)
    first = next(i for i in images if i.label.name == "NLA_399801979EDR_D0030382TRAV00006M1.LBL")
    assert first.motion_counter == (3, 382, 2) and first.instrument == "NAV_LEFT_A" and first.eye == "LEFT"
    assert first.utc_s == pytest.approx(1346530131.355)  # 2012-09-01T20:08:51.355 UTC
    assert np.allclose(first.site_T_rover[:3, 3], [-1.90435, 33.2072, 1.32141])
    assert first.camera.kind == "CAHVOR" and (first.width, first.height) == (256, 256)
    assert (first.sun_site_azimuth_deg, first.sun_site_elevation_deg) == (297.332, 65.9631)
    assert {i.site for i in images} == {3, 4} and {i.eye for i in images} == {"LEFT"}
    assert all(np.allclose(i.site_T_rover[:3, :3] @ i.site_T_rover[:3, :3].T, np.eye(3), atol=1e-9) for i in images)


def test_site_frames_chain_into_the_first(images):
    origins = site_origins(images)
    assert set(origins) == {3, 4}
    assert np.allclose(origins[4], [-43.8559, 67.1969, 1.73461])  # site 4 in site 3's frame (north, east, down)
    # the rover's forward axis in east-north-up: level (the chassis tilts a few degrees at most)
    for image in images:
        forward = enu_T_body(image, origins)[:3, 0]
        assert abs(forward[2]) < 0.2


def _similarity_2d(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, scale) of the least-squares similarity taking points a onto b (Umeyama)."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, s, vt = np.linalg.svd((b - mb).T @ (a - ma) / len(a))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return float(np.rad2deg(np.arctan2(rotation[1, 0], rotation[0, 0]))), float(np.trace(np.diag(s) @ d)
                                                                                 / (a - ma).var(axis=0).sum())


def test_the_onboard_positions_against_mslice_over_site_4(images):
    """Every (site 4, drive) the labels and MSLICE share: the onboard position relative to site
    4's origin against MSLICE's (its latitude and longitude in a Mars frame at its site 4)."""
    mslice = mslice_locations(CURIOSITY / "mslice_locations_sol0_59.xml")
    origins = site_origins(images)
    frame = LocalFrame(*mslice[(4, 0)], 0.0, body="mars")
    onboard, ground = {}, {}
    for image in images:
        key = (image.site, image.drive)
        if image.site == 4 and key in mslice and key not in onboard:
            site_4_enu = np.array([origins[4][1], origins[4][0]])  # its (north, east, down) as east, north
            onboard[key] = enu_T_body(image, origins)[:2, 3] - site_4_enu
            ground[key] = frame.to_enu(*mslice[key], 0.0)[0, :2]
    assert len(onboard) >= 80
    a, b = np.array(list(onboard.values())), np.array([ground[k] for k in onboard])
    difference = np.linalg.norm(a - b, axis=1)
    rotation_deg, scale = _similarity_2d(a, b)
    # measured: median 2.10 m, largest 2.74 m; MSLICE is the onboard track turned by 0.266 deg
    # (anticlockwise) and shrunk by 0.271 %
    assert np.median(difference) == pytest.approx(2.10, abs=0.05) and difference.max() < 3.0
    assert rotation_deg == pytest.approx(0.27, abs=0.02) and (scale - 1.0) * 100 == pytest.approx(-0.27, abs=0.02)


@pytest.mark.parametrize("change, words", [
    (("MODEL_TYPE                      = CAHVOR", "MODEL_TYPE                      = PINHOLE"),
     r"camera model type 'PINHOLE': expected CAHV, CAHVOR or CAHVORE"),
    (("ORIGIN_ROTATION_QUATERNION      = (0.188792,", "ORIGIN_ROTATION_QUATERNION      = (1.188792,"),
     r"ROVER_COORD_SYSTEM_PARMS ORIGIN_ROTATION_QUATERNION has length 1.54\d+, expected a unit quaternion"),
    (("START_TIME                        = 2012-09-01T20:08:51.355", "START_TIME = yesterday"),
     r"START_TIME 'yesterday' is not a UTC time"),
    (("GROUP                             = GEOMETRIC_CAMERA_MODEL_PARMS", "GROUP = SOMETHING_ELSE"),
     r"no camera model \(GEOMETRIC_CAMERA_MODEL_PARMS\)"),
    # found by fuzzing: each once escaped as a KeyError, ValueError, TypeError or OverflowError
    (("  LINE_SAMPLES                    = 256", "  SAMPLES = 256"), r"IMAGE has no LINE_SAMPLES"),
    (("  LINE_SAMPLES                    = 256", '  LINE_SAMPLES = "x"'),
     r"IMAGE LINE_SAMPLES is not a whole number"),
    (("ROVER_MOTION_COUNTER              = (3,382,2,0,0,0,4,0,0,0)", "ROVER_MOTION_COUNTER = 3"),
     r"ROVER_MOTION_COUNTER and its _NAME must be lists"),
    (("  ORIGIN_OFFSET_VECTOR            = (-1.90435,33.2072,1.32141)",
      "  ORIGIN_OFFSET_VECTOR            = (-1.90435,33.2072," + "9" * 400 + ")"),
     r"ROVER_COORD_SYSTEM_PARMS ORIGIN_OFFSET_VECTOR is not 3 numbers"),
])
def test_a_bad_label_is_refused_naming_it(tmp_path, change, words):
    source = CURIOSITY / "sol0026" / "NLA_399801979EDR_D0030382TRAV00006M1.LBL"
    text = source.read_text()
    old, new = change
    assert old in text
    bad = tmp_path / "bad.LBL"
    bad.write_text(text.replace(old, new).replace("END_GROUP                         = GEOMETRIC_CAMERA_MODEL_PARMS",
                                                  "END_GROUP = SOMETHING_ELSE") if "SOMETHING" in new else
                   text.replace(old, new))
    with pytest.raises(InputError, match=r"bad.LBL: " + words):
        read_pds3_label(bad)


def test_a_folder_without_labels_is_named(tmp_path):
    with pytest.raises(InputError, match=r"no rover image products"):
        read_rover_images(tmp_path)


def _two_products(tmp_path):
    """Two real products (label and browse image) of sol 26 in a folder of their own."""
    import shutil

    folder = tmp_path / "products"
    folder.mkdir()
    for stem in ("NLA_399801979EDR_D0030382TRAV00006M", "NLA_399802006EDR_D0030386TRAV00006M"):
        shutil.copy(CURIOSITY / "sol0026" / f"{stem}1.LBL", folder)
        shutil.copy(CURIOSITY / "sol0026" / f"{stem}_.jpg", folder)
    return folder


def test_each_label_finds_its_browse_image(tmp_path):
    images = read_rover_images(_two_products(tmp_path))
    assert [i.image.name for i in images] == ["NLA_399801979EDR_D0030382TRAV00006M_.jpg",
                                              "NLA_399802006EDR_D0030386TRAV00006M_.jpg"]
    assert {i.mission for i in images} == {"MSL"}


def test_an_image_whose_size_disagrees_with_its_label_is_named(tmp_path):
    import cv2

    folder = _two_products(tmp_path)
    cv2.imwrite(str(folder / "NLA_399802006EDR_D0030386TRAV00006M_.jpg"), np.zeros((128, 256), np.uint8))
    with pytest.raises(InputError, match=r"NLA_399802006EDR_D0030386TRAV00006M_.jpg: 256 x 128 px, but its label "
                                         r"NLA_399802006EDR_D0030386TRAV00006M1.LBL says 256 x 256"):
        read_rover_images(folder)


def test_products_of_two_missions_are_refused(tmp_path):
    folder = _two_products(tmp_path)
    label = folder / "NLA_399802006EDR_D0030386TRAV00006M1.LBL"
    label.write_text(label.read_text().replace('INSTRUMENT_HOST_ID                = "MSL"',
                                               'INSTRUMENT_HOST_ID                = "MER2"'))
    with pytest.raises(InputError, match=r"products of more than one mission \(MSL: .*M1.LBL, MER2: .*M1.LBL\)"):
        read_rover_images(folder)
