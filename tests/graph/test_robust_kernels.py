"""Robust kernels on multi-dimensional residuals: GTSAM weighs the whole whitened residual's norm,
so the threshold follows the factor's dimension (graph/noise.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pancam_graph.graph import noise


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
