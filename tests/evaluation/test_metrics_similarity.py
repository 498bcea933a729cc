"""The 2-D similarity fit of held-out scoring (evaluation.metrics.fit_similarity_2d)."""

import numpy as np
import pytest

from pancam_graph.evaluation.metrics import fit_similarity_2d


def test_a_turned_scaled_and_shifted_track_gives_back_its_rotation_and_scale():
    rng = np.random.default_rng(2)
    est = rng.uniform(-100, 100, (40, 2))
    angle, scale = np.deg2rad(-0.27), 0.9973
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    ref = scale * est @ rot.T + [12.0, -3.0]
    fitted_angle, fitted_scale, residuals = fit_similarity_2d(est, ref)
    assert fitted_angle == pytest.approx(angle, abs=1e-12) and fitted_scale == pytest.approx(scale, abs=1e-12)
    assert residuals.max() < 1e-9


def test_too_few_or_coincident_points_give_none():
    assert fit_similarity_2d(np.zeros((2, 2)), np.ones((2, 2))) is None
    assert fit_similarity_2d(np.zeros((5, 2)), np.ones((5, 2))) is None
