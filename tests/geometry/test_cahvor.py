"""CAHV / CAHVOR / CAHVORE camera models (geometry/cahvor.py): on the 122 real Curiosity Navcam
labels, rays back-projected and projected again land on their pixels; CAHVORE with no pupil
shift and a perspective lens is CAHVOR; a fisheye CAHVORE's moving pupil round-trips; bad
models are refused by name; and the photogrammetric conversion's residual."""

from pathlib import Path

import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.geometry.cahvor import CameraModel, to_photogrammetric

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
CURIOSITY = REAL / "curiosity_navcam_sol26_57"
needs_curiosity = pytest.mark.skipif(not CURIOSITY.is_dir(),
                                     reason=f"needs {CURIOSITY} (../shared beside the checkout)")


def _navcam_models() -> list[tuple[CameraModel, int, int]]:
    from pancam_graph.formats.pds import read_rover_images

    images = read_rover_images(CURIOSITY)
    assert {image.camera.kind for image in images} == {"CAHVOR"}
    return [(image.camera, image.width, image.height) for image in images]


def _grid(width: int, height: int, n: int = 17) -> np.ndarray:
    xs, ys = np.meshgrid(np.linspace(0.0, width - 1.0, n), np.linspace(0.0, height - 1.0, n))
    return np.column_stack([xs.ravel(), ys.ravel()])


@pytest.fixture(scope="module")
def navcam():
    return _navcam_models()


@pytest.mark.real_data
@needs_curiosity
def test_every_curiosity_navcam_model_projects_its_own_rays_back_onto_their_pixels(navcam):
    assert len(navcam) == 122 and {w for _, w, _ in navcam} == {256, 1024}
    worst = 0.0
    for model, width, height in navcam:
        pixels = _grid(width, height)
        origins, directions = model.rays(pixels)
        for range_m in (0.5, 5.0, 500.0):
            worst = max(worst, np.abs(model.project(origins + range_m * directions) - pixels).max())
        # the rays look forward, along A
        assert np.all(directions @ model.a > 0.5)
        assert model.hv_skew_deg < 0.01  # measured: at most 0.009 deg
    assert worst < 1e-6


@pytest.mark.real_data
@needs_curiosity
def test_the_distortion_is_radial_about_o_and_vanishes_on_it(navcam):
    model, width, height = next(m for m in navcam if m[1] == 1024)
    linear = CameraModel(model.c, model.a, model.h, model.v)
    on_axis = model.c + 3.0 * model.o
    assert np.allclose(model.project(on_axis[None]), linear.project(on_axis[None]), atol=1e-9)
    corner = model.rays(np.array([[0.0, 0.0]]))[1][0]
    shift = np.linalg.norm(model.project((model.c + corner)[None]) - linear.project((model.c + corner)[None]))
    assert 0.5 < shift < 5.0  # Navcam: a pixel or two at the corner of a full frame


def _cahvore(model: CameraModel, e=(0.0, 0.0, 0.0), linearity=1.0) -> CameraModel:
    return CameraModel(model.c, model.a, model.h, model.v, model.o, model.r, np.array(e), linearity)


@pytest.mark.real_data
@needs_curiosity
def test_cahvore_with_no_pupil_shift_and_a_perspective_lens_is_cahvor(navcam):
    model, width, height = navcam[0]
    same = _cahvore(model)
    pixels = _grid(width, height)
    origins, directions = model.rays(pixels)
    points = origins + 4.0 * directions
    assert np.allclose(same.project(points), model.project(points), atol=1e-9)
    o2, d2 = same.rays(pixels)
    assert np.allclose(o2, origins, atol=1e-12) and np.allclose(d2, directions, atol=1e-9)


@pytest.mark.parametrize("linearity", [0.0, 0.5, 1.0])
def test_a_cahvore_with_a_moving_pupil_round_trips(linearity):
    """A wide lens whose entrance pupil moves 1-3 cm along O with the angle (Hazcam-like):
    points on each back-projected ray, from its own origin, project onto the pixel."""
    model = CameraModel(c=[0.2, 0.1, -1.9], a=[1.0, 0.0, 0.0], h=[512.0, 600.0, 0.0], v=[512.0, 0.0, 600.0],
                        o=[0.9998, 0.0141, 0.0141], r=[0.0, -0.02, 0.003], e=[0.01, 0.005, -0.002],
                        linearity=linearity)
    pixels = _grid(1024, 1024)
    origins, directions = model.rays(pixels)
    shift = (origins - model.c) @ model.o
    assert np.ptp(shift) > 1e-3  # the pupil moves
    for range_m in (0.3, 3.0, 30.0):
        assert np.abs(model.project(origins + range_m * directions) - pixels).max() < 1e-6


@pytest.mark.parametrize("change, words", [
    ({"h": [100.0, 306.5, 120.0]}, r"H and V are .* deg apart once A is taken out: expected 90 deg within 0.5 deg"),
    ({"a": [0.9, 0.0, 0.5]}, r"A must be a unit vector"),
    ({"r": None}, r"has O and R together"),
    ({"c": [0.0, float("nan"), 0.0]}, r"C must be 3 finite numbers"),
])
def test_a_bad_model_is_refused_by_name(change, words):
    good = {"c": [0.94, 0.34, -1.92], "a": [0.880549, -0.000483697, 0.473937], "h": [112.392, 306.499, 56.2718],
            "v": [-34.0832, 3.60851, 329.709], "o": [0.881672, 0.0158892, 0.471577],
            "r": [0.000274, -0.004951, 0.021485]}
    CameraModel(**good, name="NLA_good.LBL")
    with pytest.raises(InputError, match=r"NLA_bad.LBL: (a )?camera model " + words):
        CameraModel(**(good | change), name="NLA_bad.LBL")


@pytest.mark.real_data
@needs_curiosity
def test_the_photogrammetric_conversion_of_every_navcam_model_within_0_05_px(navcam):
    """The rotation and OpenCV pinhole (k1, k2, p1, p2, k3 and the thin prism s1..s4) fitted to
    each of the 122 models reproduce its projection within 0.05 px over a 25 x 25 grid, corners
    included (largest 0.012 px on the 256 x 256 VO frames, 0.049 px on the full frames), and on
    a 61 x 61 grid of rays it was not fitted to, at 2 m and at 100 m, the same."""
    residuals = {(width, height): [] for _, width, height in navcam}
    for model, width, height in navcam:
        fitted = to_photogrammetric(model, width, height)
        residuals[(width, height)].append(fitted.residual_px)
    assert max(residuals[(256, 256)]) < 0.05 and max(residuals[(1024, 1024)]) < 0.05, residuals
    model, width, height = next(m for m in navcam if m[1] == 1024)
    fitted = to_photogrammetric(model, width, height)
    pixels = _grid(width, height, 61)
    origins, directions = model.rays(pixels)
    for range_m in (2.0, 100.0):
        error = np.linalg.norm(fitted.project(origins + range_m * directions) - pixels, axis=1)
        assert error.max() < 0.05


def test_the_camera_s_distortion_is_opencv_s():
    """Camera.project with every term against cv2.projectPoints given Camera.distortion()."""
    import cv2

    from pancam_graph.geometry.rig import Camera

    camera = Camera(1227.0, 1226.5, 523.1, 515.3, 1024, 1024, -0.0049, 0.0222, 0.0036, 0.0080, -0.003,
                    0.0011, -0.0004, 0.0009, 0.0002)
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-3, 3, (200, 2)), rng.uniform(4, 9, 200)])
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.matrix(), camera.distortion())
    np.testing.assert_allclose(camera.project(points), theirs.reshape(-1, 2), atol=1e-9)
    assert len(camera.distortion()) == 12 and len(Camera(1, 1, 0, 0, 2, 2, k3=0.1).distortion()) == 5


def test_an_opencv_camera_with_radial_distortion_is_exactly_a_cahvor():
    """from_photogrammetric: the CAHVOR projects as cv2.projectPoints does the pinhole with k1, k2
    (a tilted, shifted camera, points up to 40 deg off its axis), and converts back to it."""
    import cv2
    from scipy.spatial.transform import Rotation

    from pancam_graph.geometry.cahvor import from_photogrammetric
    from pancam_graph.geometry.rig import Camera

    camera = Camera(1724.1, 1726.0, 515.3, 509.8, 1024, 1024, k1=-0.2645, k2=0.2626)
    model_R_camera = Rotation.from_rotvec([0.3, -1.2, 0.4]).as_matrix()
    centre = np.array([0.5, -0.2, -1.9])
    model = from_photogrammetric(camera, model_R_camera, centre)
    assert model.kind == "CAHVOR"
    rng = np.random.default_rng(0)
    p_camera = np.column_stack([rng.uniform(-0.8, 0.8, (500, 2)), np.ones(500)]) * rng.uniform(2, 30, 500)[:, None]
    theirs, _ = cv2.projectPoints(p_camera, np.zeros(3), np.zeros(3), camera.matrix(), camera.distortion())
    np.testing.assert_allclose(model.project(p_camera @ model_R_camera.T + centre), theirs.reshape(-1, 2), atol=1e-9)
    back = to_photogrammetric(model, 1024, 1024)
    assert back.residual_px < 1e-6
    np.testing.assert_allclose([back.camera.fx, back.camera.fy, back.camera.cx, back.camera.cy, back.camera.k1,
                                back.camera.k2], [1724.1, 1726.0, 515.3, 509.8, -0.2645, 0.2626], atol=1e-8)
    np.testing.assert_allclose(back.model_R_camera, model_R_camera, atol=1e-10)
    with pytest.raises(InputError, match=r"only radial k1, k2 distortion has a CAHVOR form"):
        from_photogrammetric(Camera(1724.1, 1726.0, 515.3, 509.8, 1024, 1024, p1=1e-4), model_R_camera, centre)
