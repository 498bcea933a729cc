"""CRLB and NEES: the bound against a chain whose variance is known by hand, the NEES test
against samples drawn from known covariances, and the fields a run writes."""

import gtsam
import numpy as np
import pytest

from pancam_graph.errors import GraphError
from pancam_graph.evaluation.consistency import (
    NEES_BOUND_99,
    PointsByTrack,
    anees_band,
    consistency,
    crlb_position_covariances,
    last_stop_summary,
    monte_carlo_summary,
    nees_along_run,
)
from pancam_graph.graph.keys import X
from pancam_graph.graph.smoother import RelinearizeThresholds, Smoother
from pancam_graph.store.documents import metrics_document


def test_crlb_of_a_chain_is_the_sum_of_its_step_variances():
    # start prior 0.1 m, three 1 m steps of 0.02 m each, rotations pinned: var_k = 0.1^2 + k 0.02^2
    tight = 1e-9
    smoother = Smoother(RelinearizeThresholds(0.02, 0.1, 0.05, 2e-5), relinearize_skip=1, window_m=np.inf,
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
    # with the smoother's Cholesky (GPS runs), the same bound; where Cholesky fails, QR's
    smoother.factorization = "CHOLESKY"
    np.testing.assert_allclose(crlb_position_covariances(smoother, [0, 1, 2, 3], truth, {}), covs, rtol=1e-9)
    asked = []
    real = Smoother._marginals_at

    def cholesky_fails(self, values, keys, factorization):
        asked.append(factorization)
        if factorization == "CHOLESKY":
            raise GraphError("indeterminate")
        return real(self, values, keys, factorization)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Smoother, "_marginals_at", cholesky_fails)
        np.testing.assert_allclose(crlb_position_covariances(smoother, [0, 1, 2, 3], truth, {}), covs, rtol=1e-9)
    assert asked == ["CHOLESKY", "QR"]


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


def test_nees_along_a_run_puts_one_percent_outside_the_99_percent_ellipsoid_when_the_covariance_is_right():
    rng = np.random.default_rng(7)
    n = 20000
    covs = np.tile(np.diag([0.04, 0.01, 0.09]), (n, 1, 1))
    errors = rng.multivariate_normal(np.zeros(3), covs[0], size=n)
    inliers = rng.integers(20, 400, size=n)
    right = nees_along_run(errors, np.zeros((n, 3)), covs, inliers)
    assert NEES_BOUND_99 == pytest.approx(11.345, abs=1e-3)  # chi-square, 3 dof, 99 %
    assert right.outside_99_fraction == pytest.approx(0.01, abs=0.002)  # 200 +- 14 stops
    over = nees_along_run(errors, np.zeros((n, 3)), covs / 4, inliers)  # claims half the sigma it has
    assert over.outside_99_fraction == pytest.approx(0.418, abs=0.01)  # P(chi2_3 > 11.345 / 4) = 0.4176
    worst = over.largest()
    assert over.nees[worst[0]] == over.nees.max() and list(over.nees[worst]) == sorted(over.nees[worst])[::-1]
    listed = over.as_dict()["nees_largest"][0]
    assert listed == {"stop": worst[0], "nees": over.nees.max(), "vo_inliers": int(inliers[worst[0]])}
    assert over.as_dict()["nees_last"] == over.nees[-1] == pytest.approx(4 * right.nees[-1])


def test_the_last_stops_nees_over_independent_runs_has_an_exact_band():
    rng = np.random.default_rng(3)
    cov = np.diag([0.04, 0.01, 0.09])
    runs = 30
    last = [nees_along_run(rng.multivariate_normal(np.zeros(3), cov, size=(1, )), np.zeros((1, 3)), cov[None],
                           np.array([-1])).last for _ in range(runs)]
    right = last_stop_summary(last)
    assert right["band"] == pytest.approx(anees_band(runs)) and right["covariance"] == "consistent"
    assert last_stop_summary([4 * v for v in last])["covariance"] == "over-confident"  # claims half its sigma
    assert last_stop_summary([v / 4 for v in last])["covariance"] == "under-confident"


@pytest.mark.slow
def test_run_writes_crlb_efficiency_and_anees(short_run):
    doc = metrics_document(short_run)
    for name, entry in doc["configs"].items():
        assert entry["crlb_rms_m"] > 0 and np.isfinite(entry["anees"]), name
        assert entry["efficiency"] == pytest.approx(entry["rmse_m"] / entry["crlb_rms_m"])
    for name, c in short_run.configurations.items():  # each stop's NEES, from the same covariances
        assert c.nees.nees[-1] == pytest.approx(doc["configs"][name]["nees_last"])
        assert np.mean(c.nees.nees[1:]) / 3 == pytest.approx(doc["configs"][name]["anees"], rel=0.05), name
    # sites constrain the chain: their bound is far below VO alone
    assert doc["configs"]["vo_sites"]["crlb_rms_m"] < 0.7 * doc["configs"]["vo"]["crlb_rms_m"]


def test_points_by_track_are_the_truths_rows_of_those_tracks_only():
    truth = np.arange(30.0).reshape(10, 3)
    tracks = np.array([2, 5, 9])
    points = PointsByTrack(tracks, truth[tracks])
    for t in tracks:
        np.testing.assert_array_equal(points[t], truth[t])
    assert list(points) == [2, 5, 9] and len(points) == 3
    for missing in (0, 3, 10):
        with pytest.raises(KeyError):
            points[missing]
