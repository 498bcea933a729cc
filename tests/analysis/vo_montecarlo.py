"""A test oracle: Monte Carlo of our own stereo VO (`frontend.stereo_vo.StereoVO`) on the closed form's
geometry, to check the VO error growth of (3.12)-(3.13) against the estimator itself."""

from __future__ import annotations

import gtsam
import numpy as np

from pancam_graph.analysis.design import Assumptions, fov_grid
from pancam_graph.config import EstimatorConfig
from pancam_graph.errors import EvaluationError
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.geometry.rig import Rig
from pancam_graph.records import StereoObservations


def vo_monte_carlo(rig: Rig, a: Assumptions, stops: int, trials: int, seed: int = 0, fov_deg: float | None = None,
                   elevation_m: float = 0.25) -> np.ndarray:
    """DRMS horizontal position error (m) at stops 1..n over `trials` runs of straight VO.

    Every step sees the closed form's feature grid afresh, observed at both of its stops with
    independent pixel noise `a.sigma_px` on (u_left, u_right, v): the closed form's assumptions,
    run through the real estimator (PnP RANSAC + two-stop bundle adjustment) and chained as the
    pipeline chains it.

    The closed form is planar (Y constant at camera height, so the rows v carry no range
    information). Points exactly at camera height image on one row, which PnP cannot use, so
    the grid alternates `elevation_m` above and below it; on level ground far below the camera,
    v would add range information the planar model leaves out (about 15 % less error)."""
    rng = np.random.default_rng(seed)
    if fov_deg is None:
        fov_deg = float(np.rad2deg(2 * np.arctan(rig.wac.width / 2 / rig.wac.fx)))
    body_T_left = rig.body_T_left(0.0, 0.0)
    # the closed form's grid has no range cut-off of its own, and every point is an inlier
    vo = StereoVO.configured(rig, body_T_left, a.sigma_px, EstimatorConfig(
        vo_max_step_m=10 * a.vo_step_m, vo_pnp_iterations=200, vo_max_range_m=1e9))
    calibration = rig.stereo_calibration()
    grid = fov_grid(fov_deg, a.vo_max_range_m, a.vo_feature_spacing_m, a.vo_min_range_m)
    ahead = grid - np.array([0.0, a.vo_step_m])
    half = np.deg2rad(fov_deg) / 2
    seen = (ahead[:, 1] > 0) & (np.abs(np.arctan2(ahead[:, 0], ahead[:, 1])) <= half) & (
        np.hypot(*ahead.T) >= a.vo_min_range_m)
    elevation = elevation_m * np.where(np.arange(seen.sum()) % 2 == 0, 1.0, -1.0)
    points_prev = np.column_stack([grid[seen, 0], elevation, grid[seen, 1]])  # left camera frame
    step = gtsam.Pose3(gtsam.Rot3(), np.array([a.vo_step_m, 0.0, 0.0]))  # body: x forward
    left_prev = gtsam.StereoCamera(gtsam.Pose3(), calibration)
    left_curr = gtsam.StereoCamera(body_T_left.inverse().compose(step).compose(body_T_left), calibration)
    tracks = np.arange(len(points_prev))

    def observe(camera: gtsam.StereoCamera) -> StereoObservations:
        uvv = np.array([camera.project(p).vector() for p in points_prev])
        return StereoObservations(tracks, uvv + rng.normal(0.0, a.sigma_px, uvv.shape))

    errors = np.zeros((trials, stops))
    for trial in range(trials):
        pose = gtsam.Pose3()
        for k in range(stops):
            result = vo.estimate(observe(left_prev), observe(left_curr))
            if not result.ok:
                raise EvaluationError(f"Monte Carlo VO failed in trial {trial}, step {k}: {result.reason}")
            pose = pose.compose(result.prev_T_curr)
            errors[trial, k] = np.hypot(pose.x() - a.vo_step_m * (k + 1), pose.y())
    return np.sqrt(np.mean(errors**2, axis=0))
