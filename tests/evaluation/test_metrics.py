import gtsam
import numpy as np
import pytest

from pancam_graph.evaluation.metrics import align, compare, decimated_length, kitti_drift


def _curve(n=200):
    s = np.linspace(0, 1, n)
    return np.column_stack([300 * s, 80 * np.sin(3 * s), 5 * s**2])


def _poses(p):
    out = np.tile(np.eye(4), (len(p), 1, 1))
    out[:, :3, 3] = p
    return out


def test_constant_offset_gives_exact_errors():
    ref = _curve()
    m = compare(ref + [3.0, 4.0, 0.0], ref)
    assert m.average_error_m == pytest.approx(5.0)
    assert m.closure_error_m == pytest.approx(5.0)
    assert m.relative_closure_pct == pytest.approx(100 * 5.0 / m.reference_length_m)
    assert m.length_ratio == pytest.approx(1.0)
    assert compare(ref + [3.0, 4.0, 0.0], ref, "se3").ate_rmse_m == pytest.approx(0.0, abs=1e-9)


def test_shortened_trajectory_has_length_ratio_below_one():
    ref = _curve()
    m = compare(ref * 0.9, ref)
    assert m.length_ratio == pytest.approx(0.9)


def test_se3_alignment_removes_rigid_motion_but_not_scale():
    ref = _curve()
    rot = gtsam.Rot3.Ypr(0.3, 0.05, -0.02).matrix()
    moved = ref @ rot.T + [10, -5, 2]
    aligned, kind = align(moved, ref, "se3")
    assert kind == "se3"
    np.testing.assert_allclose(aligned, ref, atol=1e-8)
    assert compare(ref * 1.1, ref, "se3").ate_rmse_m > 1.0  # never silently Sim(3)


def test_straight_line_falls_back_to_yaw_alignment_and_says_so():
    ref = np.column_stack([np.linspace(0, 100, 50), np.zeros(50), np.zeros(50)])
    _, kind = align(ref + [1, 2, 0], ref, "se3")
    assert kind.startswith("yaw")


def test_kitti_drift_zero_for_perfect_and_known_for_scaled():
    ref = _curve(400)
    assert kitti_drift(_poses(ref), _poses(ref))[0] == pytest.approx(0.0, abs=1e-9)
    # 2 % scale error on a straight line: 2 % of every segment (on a curve, 2 % of the chord)
    line = np.column_stack([np.linspace(0, 300, 400), np.zeros(400), np.zeros(400)])
    t_pct, _, segs = kitti_drift(_poses(line * 1.02), _poses(line))
    # KITTI divides by the nominal length; the segment ends at the first sample past it
    # (samples every ~0.8 m here), so at most 1 % above 2 %.
    assert 2.0 <= t_pct <= 2.02
    assert segs == [100.0, 200.0, 300.0]


def test_decimated_length_ignores_gps_noise():
    rng = np.random.default_rng(0)
    line = np.column_stack([np.linspace(0, 500, 400), np.zeros(400), np.zeros(400)])
    noisy = line + rng.normal(0, 2.0, line.shape)
    raw = np.sum(np.linalg.norm(np.diff(noisy, axis=0), axis=1))
    assert raw > 2.0 * 500.0  # the noise dominates a naive sum
    assert decimated_length(noisy, 20.0) == pytest.approx(500.0, rel=0.04)


def test_every_comparison_carries_the_unaligned_and_the_se3_aligned_ate():
    """Whatever alignment `ate_rmse_m` used: a rigidly moved copy is off by its offsets' RMS
    unaligned and by nothing once SE(3)-aligned; a scaled copy keeps an aligned error."""
    ref = _curve()
    rot = gtsam.Rot3.Ypr(0.02, 0.0, 0.0).matrix()
    moved = ref @ rot.T + [3.0, -4.0, 1.0]
    for alignment in ("none", "se3"):
        m = compare(moved, ref, alignment)
        assert m.ate_unaligned_rmse_m == pytest.approx(np.sqrt(np.mean(np.sum((moved - ref) ** 2, axis=1))))
        assert m.ate_se3_rmse_m == pytest.approx(0.0, abs=1e-8)
    assert compare(ref * 1.01, ref).ate_se3_rmse_m > 0.3
