"""A tie's matching error in the estimator's weights (graph/noise.py's stereo_tie): the image
matcher's error moves both eyes' pixels of a later site's view alike, and weighted as it is,
the two sites' relative pose is as uncertain as its covariance says."""

import gtsam
import numpy as np

from pancam_graph.geometry.rig import rig_preset
from pancam_graph.graph import factors, noise, tie_matching
from pancam_graph.graph.keys import L, X

RIG = rig_preset("exomars")
CALIBRATION = RIG.stereo_calibration()
MOUNT = gtsam.Pose3(gtsam.Rot3.Ypr(-np.pi / 2, 0.0, -np.pi / 2), np.array([0.0, 0.0, 1.5]))  # looks along x
SITES = (gtsam.Pose3(), gtsam.Pose3(gtsam.Rot3.Yaw(0.1), np.array([8.0, 1.0, 0.0])))


def _relative_pose_nees(tie_sigma_px: float, weighted_sigma_px: float, draws: int, seed: int,
                        later_views: int = 1) -> float:
    """The mean NEES (6 dof) of the later site's pose over `draws` two-site graphs of 40 ties,
    the later site's `later_views` views of each off by one matching error of `tie_sigma_px` per
    axis in both eyes, each weighted as a tie `weighted_sigma_px` per axis."""
    rng = np.random.default_rng(seed)
    sigma_px = 0.3
    later = noise.stereo_tie(sigma_px, weighted_sigma_px)
    first = noise.stereo_pixels(sigma_px)
    nees = []
    for _ in range(draws):
        points = np.column_stack([rng.uniform(20, 50, 40), rng.uniform(-10, 10, 40), rng.uniform(-1.5, 1.0, 40)])
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose3(X(0), SITES[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values.insert(X(0), SITES[0])
        values.insert(X(1), SITES[1].compose(gtsam.Pose3.Expmap(rng.normal(0.0, 0.01, 6))))
        for j, point in enumerate(points):
            values.insert(L(j), point + rng.normal(0.0, 0.1, 3))
            tie = rng.normal(0.0, tie_sigma_px, 2)
            later_error = np.array([tie[0], tie[0], tie[1]])
            for site, model, error in ((0, first, np.zeros(3)), *[(1, later, later_error)] * later_views):
                true = gtsam.StereoCamera(SITES[site].compose(MOUNT), CALIBRATION).project(point)
                uvv = np.array([true.uL(), true.uR(), true.v()]) + rng.normal(0.0, sigma_px, 3) + error
                graph.add(factors.stereo(site, j, uvv, CALIBRATION, MOUNT, model))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        covariance = gtsam.Marginals(graph, result).marginalCovariance(X(1))
        error = gtsam.Pose3.Logmap(SITES[1].between(result.atPose3(X(1))))
        nees.append(float(error @ np.linalg.solve(covariance, error)))
    return float(np.mean(nees))


def test_a_tie_weighted_with_its_matching_error_gives_a_consistent_relative_pose():
    """Ties 50 m apart (the matcher's 0.65 px per axis), 60 draws: weighted as pixel noise alone
    the later site's mean NEES is 13.6 (6 expected; 13.6-18.0 over seeds 0-3), with the matching
    error in both eyes 5.5 (5.5-6.8)."""
    tie_sigma_px = tie_matching.sigma_px(50.0)
    assert abs(tie_sigma_px - 0.65) < 0.01
    as_pixel_noise = _relative_pose_nees(tie_sigma_px, 0.0, 60, 3)
    as_ties = _relative_pose_nees(tie_sigma_px, tie_sigma_px, 60, 3)
    assert 4.5 < as_ties < 7.5
    assert as_pixel_noise > 12.0


def test_views_that_share_a_tie_take_its_error_as_many_times_over():
    """A site's views of a tie share its one matching error (overlapping frames; an HRC view is
    the same error in HRC pixels): two views a tie, each weighted with the error as its own, give
    a mean NEES of 8.6 (6 expected; 8.1-8.9 over seeds 0-3), weighted with it sqrt(2) times over
    6.0 (5.7-6.3)."""
    tie_sigma_px = tie_matching.sigma_px(50.0)
    each_its_own = _relative_pose_nees(tie_sigma_px, tie_sigma_px, 60, 3, later_views=2)
    shared = _relative_pose_nees(tie_sigma_px, tie_sigma_px * np.sqrt(2.0), 60, 3, later_views=2)
    assert 4.5 < shared < 7.5
    assert each_its_own > 7.5
