"""Robust kernels on multi-dimensional residuals: GTSAM weighs the whole whitened residual's norm,
so the threshold follows the factor's dimension (graph/noise.py); and iSAM2 weighs a factor where
it linearized it, not where the estimate is (Smoother.robust_weights)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from pancam_graph.graph import noise
from pancam_graph.graph.keys import L
from pancam_graph.graph.smoother import RelinearizeThresholds, Smoother


@pytest.mark.parametrize("dim", [2, 3])
def test_an_inlier_is_down_weighted_as_often_as_in_one_dimension(dim):
    rng = np.random.default_rng(7)
    k = 1.345
    one_d = np.mean(np.abs(rng.standard_normal(200_000)) > k)
    norms = np.linalg.norm(rng.standard_normal((200_000, dim)), axis=1)
    assert np.mean(norms > noise.norm_threshold(k, dim)) == pytest.approx(one_d, abs=0.005)
    # k itself on the norm would down-weight most inliers (61 % of 3-dof, 40 % of 2-dof)
    assert np.mean(norms > k) > 0.39


def test_the_factor_noise_model_carries_the_dimension_threshold():
    model = noise.robust("huber", noise.stereo_pixels(0.5), 1.345)
    # one sigma on each of three axes is an ordinary inlier: full weight
    assert model.robust().weight(np.sqrt(3.0)) == pytest.approx(1.0)
    threshold = noise.norm_threshold(1.345, 3)
    assert model.robust().weight(2.0 * threshold) == pytest.approx(0.5)
    assert noise.robust("huber", noise.pose_sigmas(np.ones(3), np.ones(3)), 1.345).robust().weight(
        np.sqrt(6.0)) == pytest.approx(1.0)
    base = noise.stereo_pixels(0.5)
    assert noise.robust("none", base, None) is base


def _landmark_pulled_two_ways(translation_threshold_m: float) -> Smoother:
    """A landmark with a robust prior at the origin and a Gaussian one 5 cm away (both 1 cm),
    started 20 cm out: the robust prior's residual is 20 sigma where iSAM2 linearizes it."""
    thresholds = RelinearizeThresholds(rotation_rad=0.01, translation_m=translation_threshold_m, scalar=0.01,
                                       calibration=0.01)
    smoother = Smoother(thresholds, relinearize_skip=1, window_m=np.inf, wildfire_threshold=0.0)
    robust = noise.robust("huber", gtsam.noiseModel.Isotropic.Sigma(3, 0.01), 1.345)
    smoother.add(gtsam.PriorFactorPoint3(L(0), np.zeros(3), robust))
    smoother.add(gtsam.PriorFactorPoint3(L(0), np.array([0.05, 0.0, 0.0]), gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
    smoother.insert(L(0), np.array([0.2, 0.0, 0.0]))
    smoother.update()
    return smoother


def test_a_robust_factor_is_weighed_where_isam2_linearized_it():
    k = noise.norm_threshold(1.345, 3)
    # the move (15 cm) stays under a 1 m threshold: iSAM2 keeps the 20-sigma linearization
    stale = _landmark_pulled_two_ways(1.0)
    weights = stale.robust_weights()
    estimate = stale.point(L(0))
    assert weights.at_linearization == pytest.approx([k / 20.0])
    assert estimate[0] == pytest.approx(0.05 / (1.0 + k / 20.0))  # the weighted mean the stale weight gives
    assert weights.at_estimate == pytest.approx([k / (100.0 * estimate[0])])
    assert weights.at_estimate[0] > 3.0 * weights.at_linearization[0]
    # relinearized as it moves (a micrometre threshold), the weights meet at Huber's solution
    fresh = _landmark_pulled_two_ways(1e-6)
    for _ in range(30):
        fresh.update()
    weights = fresh.robust_weights()
    assert weights.at_linearization == pytest.approx(weights.at_estimate, rel=1e-3)
    # Huber's fixed point: x = 0.05 / (1 + k / r) with r = 100 x sigmas
    x = fresh.point(L(0))[0]
    assert x == pytest.approx(0.05 / (1.0 + k / (100.0 * x)), rel=1e-3)
