"""CRLB and NEES: the bound against a chain whose variance is known by hand, the NEES test
against samples drawn from known covariances, and the fields a run writes."""

import gtsam
import numpy as np
import pytest

from pancam_graph.evaluation.consistency import anees_band, consistency, crlb_position_covariances, monte_carlo_summary
from pancam_graph.graph.keys import X
from pancam_graph.graph.smoother import RelinearizeThresholds, Smoother
from pancam_graph.solve.results import metrics_document


def test_crlb_of_a_chain_is_the_sum_of_its_step_variances():
    # start prior 0.1 m, three 1 m steps of 0.02 m each, rotations pinned: var_k = 0.1^2 + k 0.02^2
    tight = 1e-9
    smoother = Smoother(RelinearizeThresholds(0.02, 0.1, 0.05), relinearize_skip=1, window_m=np.inf,
                        wildfire_threshold=0.001)
    smoother.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([tight] * 3 + [0.1] * 3))))
    smoother.insert(X(0), gtsam.Pose3())
    smoother.update()
    step = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))
    for k in range(3):
        smoother.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), step, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([tight] * 3 + [0.02] * 3))))
        smoother.insert(X(k + 1), step)
        smoother.update()
    # the truth need not satisfy the measurements: the bound is the information at the truth
    truth = np.stack([gtsam.Pose3(gtsam.Rot3(), np.array([k + 0.05 * k, 0.01, 0.0])).matrix() for k in range(4)])
    covs = crlb_position_covariances(smoother, [0, 1, 2, 3], truth, {})
    for k in range(4):
        assert covs[k] == pytest.approx((0.01 + k * 0.0004) * np.eye(3), rel=1e-6)


def test_anees_tells_right_from_overconfident_covariances():
    rng = np.random.default_rng(1)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.02, 0.0], [0.0, 0.0, 0.09]])
    runs_right, runs_over = [], []
    for _ in range(40):
        errors = rng.multivariate_normal(np.zeros(3), cov, size=50)
        truth = np.zeros((50, 3))
        covs = np.tile(cov, (50, 1, 1))
        runs_right.append(consistency(errors, truth, covs, covs))
        runs_over.append(consistency(errors, truth, covs / 2, covs))
    right, over = monte_carlo_summary(runs_right), monte_carlo_summary(runs_over)
    assert right["covariance"] == "consistent" and right["efficiency"] == pytest.approx(1.0, abs=0.05)
    assert over["covariance"] == "over-confident" and over["anees"] == pytest.approx(2.0, abs=0.1)
    # chi2(90) / 90 at 2.5 % and 97.5 %, by the Wilson-Hilferty approximation
    n, z = 90, 1.959964
    wilson_hilferty = [(1 - 2 / (9 * n) + sign * z * np.sqrt(2 / (9 * n))) ** 3 for sign in (-1, 1)]
    assert anees_band(30) == pytest.approx(wilson_hilferty, abs=1e-3)


@pytest.mark.slow
def test_run_writes_crlb_efficiency_and_anees(short_run):
    doc = metrics_document(short_run)
    for name, entry in doc["configs"].items():
        assert entry["crlb_rms_m"] > 0 and np.isfinite(entry["anees"]), name
        assert entry["efficiency"] == pytest.approx(entry["rmse_m"] / entry["crlb_rms_m"])
    # sites constrain the chain: their bound is far below VO alone
    assert doc["configs"]["vo_sites"]["crlb_rms_m"] < 0.7 * doc["configs"]["vo"]["crlb_rms_m"]
