import cv2
import gtsam
import numpy as np
import pytest

from pancam_graph.geometry.rig import Camera, project_rectified, rig_preset, triangulate_rectified


def test_projection_matches_hand_computed_pixels():
    cam = Camera(fx=1000.0, fy=1000.0, cx=500.0, cy=400.0, width=1024, height=1024)
    # x/z = 0.1, y/z = -0.05 -> (500 + 100, 400 - 50)
    np.testing.assert_allclose(cam.project([[0.2, -0.1, 2.0]]), [[600.0, 350.0]], atol=1e-12)


def test_distortion_matches_hand_computed_pixels_and_opencv():
    cam = Camera(1000.0, 1000.0, 500.0, 400.0, 1024, 1024, k1=0.1, k2=0.01, p1=0.001, p2=0.002)
    # By hand: r2 = 0.0125, radial = 1.0012515625,
    # xd = 0.1 * radial + 2 p1 x y + p2 (r2 + 2 x^2) = 0.10018015625
    # yd = -0.05 * radial + p1 (r2 + 2 y^2) + 2 p2 x y = -0.050065078125
    np.testing.assert_allclose(cam.project([[0.2, -0.1, 2.0]]), [[600.18015625, 349.934921875]], atol=1e-9)
    pts = np.array([[0.3, 0.2, 1.5], [-0.4, 0.1, 2.5], [0.05, -0.3, 1.1]])
    cv_uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.matrix(), cam.distortion())
    np.testing.assert_allclose(cam.project(pts), cv_uv.reshape(-1, 2), atol=1e-9)


def test_exomars_preset_matches_design_table():
    rig = rig_preset("exomars")
    assert rig.wac.fx == pytest.approx(1724.1, abs=0.1)  # 580 urad/px
    assert rig.hrc.fx == pytest.approx(12195.1, abs=0.1)  # 82 urad/px
    assert np.degrees(rig.wac.width / rig.wac.fx) == pytest.approx(34.0, abs=0.1)
    assert np.degrees(rig.hrc.width / rig.hrc.fx) == pytest.approx(4.81, abs=0.01)
    left = rig.body_T_left(0, 0).translation()
    right = left + np.array([0.0, -rig.baseline_m, 0.0])
    hrc = rig.body_T_hrc(0, 0).translation()
    assert np.linalg.norm(hrc - left) == pytest.approx(0.404)
    assert np.linalg.norm(hrc - right) == pytest.approx(0.096)
    assert left[2] == pytest.approx(1.5)


def test_mast_kinematics_pan_and_tilt():
    rig = rig_preset("mer_navcam")
    axis = rig.body_T_left(0.0, 0.0).rotation().matrix()[:, 2]  # optical axis in the body
    np.testing.assert_allclose(axis, [1, 0, 0], atol=1e-12)
    axis = rig.body_T_left(np.pi / 2, 0.0).rotation().matrix()[:, 2]
    np.testing.assert_allclose(axis, [0, 1, 0], atol=1e-12)  # pan +90 deg looks left
    axis = rig.body_T_left(0.0, np.radians(30)).rotation().matrix()[:, 2]
    np.testing.assert_allclose(axis, [np.cos(np.radians(30)), 0, 0.5], atol=1e-12)  # tilt up
    # image x (right) stays horizontal under pan and tilt
    x_axis = rig.body_T_left(0.7, -0.4).rotation().matrix()[:, 0]
    assert x_axis[2] == pytest.approx(0.0, abs=1e-12)


def test_point_ahead_projects_right_of_centre_in_left_camera():
    rig = rig_preset("exomars")
    body_T_left = rig.body_T_left(0.0, 0.0)
    p_body = np.array([10.0, 0.0, rig.mast_height_m])  # 10 m ahead at camera height
    p_cam = body_T_left.transformTo(p_body)
    u, v = rig.wac.project(p_cam[None])[0]
    assert u == pytest.approx(rig.wac.cx + rig.wac.fx * 0.25 / 10.0)
    assert v == pytest.approx(rig.wac.cy)


def test_triangulation_follows_seed_eq_2_28():
    rig = rig_preset("exomars")
    cam = rig.wac
    # x = u0 + 100, x' = u0 + 50, y = v0 - 100: d = 50 px
    p = triangulate_rectified([cam.cx + 100], [cam.cx + 50], [cam.cy - 100], cam, 0.5)[0]
    # X = B (x - u0) / d = 1.0, Y = B (y - v0) / d = -1.0, Z = B f / d = 0.5 * 1724.14 / 50
    np.testing.assert_allclose(p, [1.0, -1.0, 0.5 * cam.fx / 50.0], rtol=1e-12)
    assert np.isnan(triangulate_rectified([10.0], [12.0], [5.0], cam, 0.5)).all()


def test_triangulation_inverts_projection():
    rig = rig_preset("exomars")
    cam = rig.wac
    p = np.array([[1.5, -0.4, 12.0], [-3.0, 0.8, 25.0]])
    uv = cam.project(p, distort=False)
    u_right = uv[:, 0] - cam.fx * rig.baseline_m / p[:, 2]
    np.testing.assert_allclose(triangulate_rectified(uv[:, 0], u_right, uv[:, 1], cam, 0.5), p, rtol=1e-10)


def test_rectified_projection_is_gtsams_stereo_camera_and_undoes_triangulation():
    rig = rig_preset("exomars")
    cam, baseline = rig.wac, rig.baseline_m
    rng = np.random.default_rng(3)
    points = rng.uniform([-5.0, -3.0, 1.5], [5.0, 3.0, 40.0], size=(50, 3))
    uvv = project_rectified(points, cam, baseline)
    stereo = gtsam.StereoCamera(gtsam.Pose3(), rig.stereo_calibration())
    for p, row in zip(points, uvv, strict=True):
        expected = stereo.project2(p)
        np.testing.assert_allclose(row, [expected.uL(), expected.uR(), expected.v()], rtol=0, atol=1e-9)
    np.testing.assert_allclose(triangulate_rectified(*uvv.T, cam, baseline), points, rtol=1e-12)
    assert np.isnan(project_rectified(np.array([[1.0, 0.0, -2.0]]), cam, baseline)).all()  # behind
