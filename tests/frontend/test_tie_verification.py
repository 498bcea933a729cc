"""The tie verification's allowance for the stereo pair's calibration (frontend/ties.py): a
turn of the right camera about the vertical biases both sites' ranges alike, and the rigid
motion the true ties give then stands off the prediction by more than its noise."""

import gtsam
import numpy as np
import pytest

from pancam_graph.frontend.panorama import PanoramaView, SitePanorama
from pancam_graph.frontend.ties import Tie, TieMatcher
from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph.tie_gate import RelativePose, site_points
from pancam_graph.kinds.stereo_calibration import StereoCalibrationSettings
from pancam_graph.sim.errors import TrueRig

RIG = rig_preset("exomars")
SIGMA_PX = 0.3
CALIBRATION_SIGMAS = StereoCalibrationSettings().sigmas()  # 0.01 deg a rotation
# the right camera turned about the vertical by 2.2e-4 rad (1.3 sigma; 0.38 px of disparity),
# what rendered short_trail seed 1 drew, where the matcher lost every tie before
TURN_RAD = -2.2e-4
A_T_B = gtsam.Pose3(gtsam.Rot3.Yaw(0.2), np.array([34.0, 3.0, 0.4]))


def _sites(rng, turn_rad: float = TURN_RAD):
    """Site a looking ahead, site b 34 m on looking back, the ground between them seen by both
    through the pair turned by turn_rad: (found ties, a's points, a, b)."""
    pair = TrueRig(RIG.wac, RIG.wac, RIG.baseline_m, gtsam.Rot3.Expmap(np.array([0.0, turn_rad, 0.0])).matrix())
    mount_a = RIG.body_T_left(np.deg2rad(10.0), np.deg2rad(-12.0))
    mount_b = RIG.body_T_left(np.deg2rad(180.0 - 5.0), np.deg2rad(-12.0))
    x, y = np.meshgrid(np.linspace(8.0, 26.0, 14), np.linspace(-6.0, 10.0, 12))
    ground = np.column_stack([x.ravel(), y.ravel(), 0.05 * np.sin(x.ravel())])  # in a's body frame

    def seen(mount: gtsam.Pose3, p_body: np.ndarray) -> np.ndarray:
        p_cam = np.array([mount.transformTo(p) for p in p_body])
        uv, u_right = pair.observe(p_cam)
        return np.column_stack([uv[:, 0], u_right, uv[:, 1]]) + rng.normal(0.0, SIGMA_PX, (len(p_cam), 3))

    a_uvv = seen(mount_a, ground)
    b_uvv = seen(mount_b, np.array([A_T_B.transformTo(p) for p in ground]))
    inside = np.all([RIG.wac.in_image(uvv[:, [0, 2]], margin_px=5) for uvv in (a_uvv, b_uvv)], axis=0)
    tracks = np.flatnonzero(inside)
    points = site_points({int(t): [(mount_a, a_uvv[t])] for t in tracks}, RIG, SIGMA_PX)
    found = [Tie(int(t), 0, a_uvv[t], 0, b_uvv[t], 0.9) for t in tracks]
    empty = np.zeros((0, 0), np.uint8)
    a = SitePanorama(0, 0, [PanoramaView(0.0, 0.0, mount_a.matrix(), empty, empty)])
    b = SitePanorama(30, 1, [PanoramaView(0.0, 0.0, mount_b.matrix(), empty, empty)])
    return found, points, a, b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_true_ties_of_a_turned_pair_are_verified_within_the_calibrations_uncertainty(seed):
    found, points, a, b = _sites(np.random.default_rng(seed))
    assert len(found) >= 40
    # the VO's prediction of a_T_b, right, and as sure of itself as a VO over 34 m is
    prediction = RelativePose(A_T_B, np.diag([3e-4, 3e-4, 3e-4, 0.02, 0.02, 0.02]) ** 2)
    trusting = TieMatcher(RIG, SIGMA_PX)
    assert trusting.verify(found, points, a, b, prediction) == []  # the turn moves the fit past the VO's sigma
    assert len(trusting.verify(*_sites(np.random.default_rng(seed), turn_rad=0.0), prediction)) == len(found)
    allowing = TieMatcher(RIG, SIGMA_PX, calibration_sigmas=CALIBRATION_SIGMAS)
    assert len(allowing.verify(found, points, a, b, prediction)) >= 0.9 * len(found)
    # the allowance is the calibration's, not a blank cheque: a prediction 1.5 m off is refused
    off = RelativePose(A_T_B.compose(gtsam.Pose3(gtsam.Rot3(), np.array([1.5, 0.0, 0.0]))), prediction.covariance)
    assert allowing.verify(found, points, a, b, off) == []


def test_an_orthoimage_is_laid_where_the_features_ray_meets_its_neighbours_ground():
    """A feature's own range error must not move where its ground is resampled (the ties then
    favoured features whose disparity error cancelled the calibration's): the ray from the
    camera through its triangulation meets the plane of its neighbours at the true ground."""
    from pancam_graph.frontend.ties import _Ground
    from pancam_graph.graph.tie_gate import SitePoint

    rng = np.random.default_rng(5)
    slope = np.array([0.1, -0.05])  # a tilted ground, z = 0.1 x - 0.05 y
    xy = rng.uniform([10.0, -3.0], [16.0, 3.0], (300, 2))
    ground = np.column_stack([xy, xy @ slope])
    noisy = ground + rng.normal(0.0, 0.01, ground.shape)  # the neighbours' own triangulation errors
    points = {k: SitePoint(p, np.eye(3)) for k, p in enumerate(noisy)}
    camera = np.array([0.0, 0.0, 1.5])
    true = np.array([13.0, 0.5, np.array([13.0, 0.5]) @ slope])
    for range_error_m in (-0.4, 0.3):  # the feature triangulated too near, too far
        seen = true + range_error_m * (true - camera) / np.linalg.norm(true - camera)
        points[-1] = SitePoint(seen, np.eye(3))
        laid = _Ground(points).where_ray_meets(camera, seen)
        assert np.linalg.norm(laid - true) < 0.05 < np.linalg.norm(seen - true) / 5


def test_the_ground_orthoimage_is_the_image_sampled_on_the_plane():
    """_ortho warps the image by the plane's homography in one call: each cell must be the mean
    of its samples, each sample the image bilinearly interpolated where the camera sees that
    point of the plane (projected here point by point, interpolated by scipy). A grid laid half a
    sample off, or a row for a column, is several DN off on this texture; OpenCV's 1/32 px
    positions a small fraction of one."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(3)
    image = gaussian_filter(rng.uniform(0.0, 255.0, (RIG.wac.height, RIG.wac.width)), 2.0)
    image = np.clip((image - image.mean()) * 12.0 + 128.0, 0, 255).astype(np.uint8)
    matcher = TieMatcher(RIG, SIGMA_PX)
    s = matcher.s
    frame_T_camera = RIG.body_T_left(np.deg2rad(15.0), np.deg2rad(-20.0)).matrix()
    normal = np.array([0.08, -0.04, 1.0]) / np.linalg.norm([0.08, -0.04, 1.0])
    e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    for centre in ([8.0, 2.0, 0.2], [12.0, 3.5, 0.0], [15.0, 4.5, 0.3]):
        for half in (s.half_cells, s.half_cells + 10):
            ortho = matcher._ortho(image, frame_T_camera, np.array(centre), e1, e2, half)
            assert ortho is not None
            n = 2 * half + 1
            offsets = ((np.arange(n * s.samples) + 0.5) / s.samples - half - 0.5) * s.cell_m
            x, y = np.meshgrid(offsets, offsets)  # x along e1 by column, y along e2 by row
            world = np.array(centre) + x[..., None] * e1 + y[..., None] * e2
            camera_T_frame = np.linalg.inv(frame_T_camera)
            in_camera = world @ camera_T_frame[:3, :3].T + camera_T_frame[:3, 3]
            uv = RIG.wac.project(in_camera.reshape(-1, 3), distort=False).reshape(*x.shape, 2)
            samples = map_coordinates(image.astype(float), [uv[..., 1], uv[..., 0]], order=1)
            expected = samples.reshape(n, s.samples, n, s.samples).mean(axis=(1, 3))
            assert np.abs(ortho - expected).max() < 0.3
