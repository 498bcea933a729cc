"""PDS4 rover image products (formats/pds4.py): what the writer puts in a label the reader gives
back, PDS's own reader (pds4_tools) reads the same image and fields from it, and a bad product
is refused in one line naming the file and what is wrong."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pancam_graph.errors import InputError
from pancam_graph.formats.pds import read_rover_images
from pancam_graph.formats.pds4 import ProductDescription, read_image, read_pds4_label, write_product
from pancam_graph.geometry.cahvor import from_photogrammetric
from pancam_graph.geometry.rig import Camera
from pancam_graph.sources import source_for
from pancam_graph.sources.pds import load

WIDTH, HEIGHT = 64, 48
CAMERA = Camera(60.0, 60.5, 31.5, 23.5, WIDTH, HEIGHT, k1=-0.2, k2=0.1)


def _pose(rotvec, position) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = position
    return out


def _product(k: int, eye: str, site: int = 1, drive: int | None = None, site_origin=None) -> ProductDescription:
    # a camera looking forward (rover x) from the mast: its x right (rover y), y down (rover z)
    rover_R_camera = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    centre = np.array([0.1, -0.2 if eye == "LEFT" else 0.2, -1.5])
    return ProductDescription(f"NAV_{eye}_{k:04d}", 1.7e9 + 60.0 * k, "TEST ROVER", f"NAV_{eye}", site,
                              k if drive is None else drive, 0, _pose([0.0, 0.0, 0.1 * k], [1.5 * k, 0.2 * k, 0.0]),
                              site_origin, from_photogrammetric(CAMERA, rover_R_camera, centre, eye))


def _image(k: int, eye: str) -> np.ndarray:
    return ((np.arange(HEIGHT * WIDTH).reshape(HEIGHT, WIDTH) + 7 * k + (eye == "RIGHT")) % 251).astype(np.uint8)


def _write(folder, stops: int = 3, rights: bool = True):
    folder.mkdir(exist_ok=True)
    for k in range(stops):
        for eye in ("LEFT", "RIGHT") if rights else ("LEFT",):
            write_product(folder, _product(k, eye), _image(k, eye))
    return folder


def test_a_written_product_reads_back_as_written(tmp_path):
    written = _product(2, "RIGHT", site=4, drive=12, site_origin=np.array([30.25, -4.5, 0.75]))
    label = write_product(tmp_path, written, _image(2, "RIGHT"))
    read = read_pds4_label(label)
    assert (read.site, read.drive, read.pose, read.eye, read.instrument, read.mission) == (
        4, 12, 0, "RIGHT", "NAV_RIGHT", "TEST ROVER")
    assert read.utc_s == pytest.approx(written.utc_s, abs=1e-6)
    np.testing.assert_allclose(read.site_T_rover, written.site_T_rover, atol=1e-12)
    assert read.site_index == 4 and read.site_origin[0] == 3
    np.testing.assert_allclose(read.site_origin[1], [30.25, -4.5, 0.75])
    for key in "cahvor":
        np.testing.assert_allclose(getattr(read.camera, key), getattr(written.camera, key), rtol=1e-15)
    assert (read.width, read.height) == (WIDTH, HEIGHT)
    np.testing.assert_array_equal(read_image(read), _image(2, "RIGHT"))


def test_pds4_tools_reads_the_products_image_and_fields(tmp_path):
    """PDS's own reader, an implementation independent of the writer's."""
    pds4_tools = pytest.importorskip("pds4_tools")
    written = _product(1, "LEFT")
    label = write_product(tmp_path, written, _image(1, "LEFT"))
    structures = pds4_tools.read(str(label), quiet=True)
    np.testing.assert_array_equal(np.asarray(structures[0].data), _image(1, "LEFT"))
    theirs = structures.label
    counter = {i.findtext("geom:index_id"): int(i.findtext("geom:index_value_number"))
               for i in theirs.findall(".//geom:Motion_Counter/geom:Motion_Counter_Index")}
    assert counter == {"SITE": 1, "DRIVE": 1, "POSE": 0}
    model = theirs.find(".//geom:CAHVOR_Model")
    axis = [float(model.findtext(f"geom:Vector_Axis/geom:{n}_unit")) for n in "xyz"]
    np.testing.assert_allclose(axis, written.camera.a, rtol=1e-15)
    radial = [float(model.findtext(f"geom:Radial_Terms/geom:c{i}")) for i in range(3)]
    assert radial == [0.0, -0.2, 0.1]


@pytest.mark.parametrize(("change", "words"), [
    (("<geom:Camera_Model_Parameters>", "<geom:Nothing>", "</geom:Camera_Model_Parameters>", "</geom:Nothing>"),
     r"no camera model \(geom:Camera_Model_Parameters\)"),
    (("<geom:model_type>CAHVOR<", "<geom:model_type>PINHOLE<"), r"camera model type 'PINHOLE'"),
    (("<geom:x_unit>", "<geom:x_unit>x"), r"geom:x_unit is .*expected a number"),
    (("<geom:index_id>SITE</geom:index_id>", "<geom:index_id>STIE</geom:index_id>"),
     r"geom:Motion_Counter names no SITE and DRIVE"),
    (("<start_date_time>", "<start_date_time>yesterday "), r"start_date_time 'yesterday .*' is not a UTC time"),
    (("<data_type>UnsignedByte<", "<data_type>IEEE754MSBSingle<"),
     r"the image's data_type is 'IEEE754MSBSingle': only 8-bit images"),
    (("<geom:qcos>", "<geom:qcos>2"),
     r"ROVER_NAV_FRAME_1_1_0's quaternion has length 2\d\.\d+, expected a unit quaternion"),
    (("<geom:z_pixel>0.0</geom:z_pixel>", "<geom:z_pixel>20.0</geom:z_pixel>"),  # H leans towards A's normal
     r"camera model H and V are .* deg apart once A is taken out: expected 90 deg within 0.5 deg"),
    (("</Product_Observational>", ""), r"not a readable PDS4 label"),
    # found by fuzzing (tests/fuzz_inputs.py): an unknown encoding, a site frame that is no number
    (("encoding='UTF-8'", "encoding='UTFabc'"), r"not a readable PDS4 label \(unknown encoding"),
    (("<local_identifier_reference>SITE_FRAME_1<", "<local_identifier_reference>SITE_FRAME_nan<"),
     r"the rover's pose is in 'SITE_FRAME_nan', expected a SITE_FRAME_<site>"),
    (("<file_name>NAV", "<file_name>" + "9" * 300), r"file_name '9{60}'\.\.\. is not a file name this system can open"),
])
def test_a_bad_pds4_label_is_refused_naming_it(tmp_path, change, words):
    label = write_product(tmp_path, _product(1, "LEFT"), _image(1, "LEFT"))
    text = label.read_text()
    for old, new in zip(change[::2], change[1::2], strict=True):
        assert old in text
        text = text.replace(old, new, 1)
    label.write_text(text)
    with pytest.raises(InputError, match=r"NAV_LEFT_0001.xml: " + words):
        read_pds4_label(label)


def test_an_image_whose_size_disagrees_with_its_label_is_named(tmp_path):
    folder = _write(tmp_path / "products", stops=2)
    (folder / "NAV_RIGHT_0001.img").write_bytes(bytes(WIDTH * HEIGHT - 3))
    with pytest.raises(InputError, match=r"NAV_RIGHT_0001.img: 3069 bytes, but its label NAV_RIGHT_0001.xml says "
                                         r"64 x 48 8-bit pixels"):
        read_rover_images(folder)


def test_a_camera_model_with_no_ray_for_some_pixels_is_refused_naming_it(tmp_path):
    """Found by fuzzing: a radial term so large that the corners have no ray reached
    least_squares as NaN residuals."""
    folder = _write(tmp_path / "products", stops=2)
    label = folder / "NAV_LEFT_0000.xml"
    label.write_text(label.read_text().replace("<geom:c1>-0.2</geom:c1>", "<geom:c1>-1e30</geom:c1>"))
    with pytest.raises(InputError, match=r"NAV_LEFT_0000.xml: the camera model gives no ray in front of it for "
                                         r"every pixel of its 64 x 48 image"):
        load(folder)


def test_other_xml_beside_the_products_is_not_a_product(tmp_path):
    folder = _write(tmp_path / "products", stops=2)
    (folder / "notes.xml").write_text("<notes>not a product</notes>")
    assert len(read_rover_images(folder)) == 4
    assert source_for(str(folder)).name == "pds"


def test_a_stop_without_its_stereo_partner_leaves_the_motion_to_the_onboard_estimate_and_says_so(tmp_path):
    folder = _write(tmp_path / "products", stops=3)
    for suffix in (".xml", ".img"):
        (folder / f"NAV_RIGHT_0001{suffix}").unlink()
    data = load(folder)
    assert set(data.estimator.configurations) == {"onboard"}
    assert [n for n in data.info.notes if "stereo" in n] == [
        "2 stereo pairs, but stop 1 (site 1, drive 1) has none: the stereo VO needs a pair at every stop; the "
        "onboard estimate carries the motion"]
    lefts = _write(tmp_path / "lefts", stops=3, rights=False)
    assert [n for n in load(lefts).info.notes if "stereo" in n] == [
        "left images only (3 products, no stereo partner): the stereo VO cannot run; the onboard estimate carries "
        "the motion"]


def test_a_pair_whose_pointing_moves_leaves_the_motion_to_the_onboard_estimate_and_says_so(tmp_path):
    folder = _write(tmp_path / "products", stops=3)
    moved = _product(2, "LEFT")
    turned = replace_camera(moved, np.deg2rad(0.5))
    write_product(folder, turned, _image(2, "LEFT"))
    data = load(folder)
    assert set(data.estimator.configurations) == {"onboard"}
    assert any("the pair's camera models or image sizes change at stop 2" in note for note in data.info.notes)


def test_a_pair_of_another_image_size_is_not_tracked_as_the_same_rig(tmp_path):
    """Found by fuzzing: a right image relabelled 96 x 32 (the same byte count) reached the
    tracker, sized for the first pair's 64 x 48, as an OpenCV error."""
    folder = _write(tmp_path / "products", stops=3)
    label = folder / "NAV_RIGHT_0001.xml"
    label.write_text(label.read_text().replace("<elements>48</elements>", "<elements>32</elements>")
                     .replace("<elements>64</elements>", "<elements>96</elements>"))
    data = load(folder)
    assert set(data.estimator.configurations) == {"onboard"}
    assert any("image sizes change at stop 1" in note for note in data.info.notes)


def replace_camera(product: ProductDescription, yaw_rad: float) -> ProductDescription:
    """The product with its camera turned about the rover's down axis."""
    from dataclasses import replace

    turn = Rotation.from_rotvec([0.0, 0.0, yaw_rad]).as_matrix()
    c = product.camera
    camera = type(c)(c.c, turn @ c.a, turn @ c.h, turn @ c.v, turn @ c.o, c.r, name=c.name)
    return replace(product, camera=camera)


def test_the_onboard_poses_of_the_labels_are_the_stops_dead_reckoning(tmp_path):
    data = load(_write(tmp_path / "products", stops=3, rights=False))
    step = data.traverse.stops[2].dead_reckoning.prev_T_curr
    # the site frame is north-east-down and the rover forward-right-down: a turn of 0.1 rad about
    # down is 0.1 rad clockwise, the body's (forward-left-up) -0.1 about up
    assert np.rad2deg(Rotation.from_matrix(step[:3, :3]).as_rotvec()[2]) == pytest.approx(-np.rad2deg(0.1))
    assert np.linalg.norm(step[:3, 3]) == pytest.approx(np.hypot(1.5, 0.2))
