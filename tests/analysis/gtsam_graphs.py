"""A test oracle: the closed-form geometries of `pancam_graph.analysis.design` as GTSAM factor
graphs, to check the closed form against GTSAM's marginals: stereo factors on (x_l, x_r, y)
with the dissertation's planar points (Y = 0, at camera height) and rigid 3-D poses.

Frames: the site frame is the straight-ahead camera's (x right, y down, z forward); a pair
pointed at bearing b (right of forward) is that frame turned by b about y.
"""

from __future__ import annotations

import gtsam
import numpy as np

from pancam_graph.analysis.design import AnalysisRig, Assumptions, tie_point_layout
from pancam_graph.graph.keys import L, X

_FIXED = gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)  # site 1 / the camera: the gauge


def _pointed_left_camera(site: gtsam.Pose3, bearing_rad: float, baseline_m: float) -> gtsam.Pose3:
    """The left camera of a pair whose centre sits at the site and looks at `bearing`."""
    rot = gtsam.Rot3.Ry(bearing_rad)
    return site.compose(gtsam.Pose3(rot, rot.rotate(np.array([-baseline_m / 2, 0.0, 0.0]))))


def stereo_point_covariance(x_m: float, z_m: float, baseline_m: float, focal_px: float, sigma_px: float
                            ) -> np.ndarray:
    """GTSAM's marginal (X, Z) covariance of a point seen once by a fixed rectified pair."""
    calibration = gtsam.Cal3_S2Stereo(focal_px, focal_px, 0.0, 0.0, 0.0, baseline_m)
    camera = gtsam.StereoCamera(gtsam.Pose3(), calibration)
    point = np.array([x_m, 0.0, z_m])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), _FIXED))
    graph.add(gtsam.GenericStereoFactor3D(camera.project(point), gtsam.noiseModel.Isotropic.Sigma(3, sigma_px),
                                          X(0), L(0), calibration))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3())
    values.insert(L(0), point)
    cov = gtsam.Marginals(graph, values).marginalCovariance(L(0))
    return cov[np.ix_([0, 2], [0, 2])]


def two_site_covariance(rig: AnalysisRig, a: Assumptions, spacing_m: float, fov_deg: float, hrc: bool = False
                        ) -> np.ndarray:
    """GTSAM's marginal (X, Z) covariance of site 2 for `design.two_site_ba`'s geometry: site 1
    fixed, site 2 a free Pose3 (rigid), each tie point a free Point3 with one stereo factor per
    site from the pair pointed at it (with `hrc`, the HRC + left-WAC pair, the WAC's sigma scaled
    to HRC pixels as in (3.11))."""
    if hrc:
        baseline, focal = rig.hrc_baseline_m, rig.hrc_focal_px
        sigmas = np.array([a.sigma_px * rig.hrc_focal_px / rig.focal_px, a.sigma_px, a.sigma_px])
    else:
        baseline, focal = rig.baseline_m, rig.focal_px
        sigmas = np.full(3, a.sigma_px)
    calibration = gtsam.Cal3_S2Stereo(focal, focal, 0.0, 0.0, 0.0, baseline)
    measurement_noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    sites = [gtsam.Pose3(), gtsam.Pose3(gtsam.Rot3.Ry(np.pi), np.array([0.0, 0.0, spacing_m]))]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), sites[0], _FIXED))
    for i, site in enumerate(sites):
        values.insert(X(i), site)
    for j, (x, z) in enumerate(tie_point_layout(spacing_m, fov_deg, a.ba_rays, a.ba_ranges)):
        point = np.array([x, 0.0, z])
        values.insert(L(j), point)
        for i, site in enumerate(sites):
            local = site.transformTo(point)
            left = _pointed_left_camera(site, float(np.arctan2(local[0], local[2])), baseline)
            measured = gtsam.StereoCamera(left, calibration).project(point)
            graph.add(gtsam.GenericStereoFactor3D(measured, measurement_noise, X(i), L(j), calibration,
                                                  site.between(left)))
    cov = gtsam.Marginals(graph, values).marginalCovariance(X(1))[3:, 3:]  # translation, body frame
    rot = sites[1].rotation().matrix()
    return (rot @ cov @ rot.T)[np.ix_([0, 2], [0, 2])]
