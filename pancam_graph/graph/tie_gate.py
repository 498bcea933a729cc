"""Whether two sites' stereo views of a tie point agree, given how well each triangulates it and
how well the graph knows the one site relative to the other.

A false match in a panorama triangulates to a random point. A fixed distance gate (metres,
growing with range) lets the ones that land near the true point through, and a single such tie
across a weakly tied gap pulls the relative heading by several sigma (denver_trail seed 10: one
false tie among 27 bent 340 -> 376 by 0.6 deg). Stereo bearings are known to ~0.3 mrad; only the
range is loose. A Mahalanobis test with both triangulation covariances (the dissertation's eq. 3.3) and the
relative-pose covariance from iSAM2 is tight across the line of sight and loose along it, as
the measurements are.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from ..geometry.rig import Rig, triangulate_rectified, triangulation_covariance
from ..records import Stop
from . import chi2

# Squared Mahalanobis distance of a 3-D disagreement that passes: chi-square, 3 dof, 99.9 %.
AGREEMENT_GATE = chi2.quantile(0.999, 3)
MIN_RANGE_M = 0.5  # a triangulation closer than this is a wrong match


@dataclass(frozen=True)
class SitePoint:
    """One site's triangulation of a track in its body frame, merged over the panorama frames
    that saw it: position (m) and covariance (m^2)."""

    p_body: np.ndarray  # (3,)
    cov_body: np.ndarray  # (3, 3)


def panorama_views(stop: Stop, rig: Rig) -> defaultdict[int, list[tuple[gtsam.Pose3, np.ndarray]]]:
    """A site panorama's stereo views of each track: (camera mount body_T_left, rectified
    (u_left, u_right, v)) per frame that saw it."""
    views: defaultdict[int, list] = defaultdict(list)
    for frame in stop.panorama:
        mount = rig.body_T_left(frame.pan_rad, frame.tilt_rad)
        for track, uvv in zip(frame.observations.track_ids, frame.observations.uvv, strict=True):
            views[int(track)].append((mount, uvv))
    return views


def site_point_cloud(stop: Stop, rig: Rig, sigma_px: float,
                     corrected: Callable[[np.ndarray], np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """A site panorama's triangulated points in the body frame (N, 3) and their covariances
    (N, 3, 3): its local elevation map; None when nothing triangulates. `corrected` maps a
    frame's pixels to what a calibrated pair would have seen (Host.site_stereo_pixels)."""
    views = panorama_views(stop, rig)
    if corrected is not None:
        views = corrected_views(views, corrected)
    points = [p for p in site_points(views, rig, sigma_px).values() if p is not None]
    if not points:
        return None
    return np.array([p.p_body for p in points]), np.array([p.cov_body for p in points])


def corrected_views(views: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]],
                    corrected: Callable[[np.ndarray], np.ndarray]) -> dict[int, list[tuple[gtsam.Pose3, np.ndarray]]]:
    """The views (as panorama_views gives them) with every pixel triple through `corrected`, in
    one call; the views themselves are left as they are (a site's are shared: sites._RECENT_SITES)."""
    tracks = [(track, mount) for track, vs in views.items() for mount, _ in vs]
    if not tracks:
        return views
    uvv = corrected(np.array([m for vs in views.values() for _, m in vs], dtype=float))
    out: defaultdict[int, list] = defaultdict(list)
    for (track, mount), pixels in zip(tracks, uvv, strict=True):
        out[track].append((mount, pixels))
    return out


def site_points(views: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]], rig: Rig, sigma_px: float
                ) -> dict[int, SitePoint | None]:
    """Merge one site's stereo views (camera mount body_T_left, rectified (u_left, u_right, v))
    of each track. None for a track when a view does not triangulate in front of the camera or
    the views disagree with each other: with two views there is no telling which one is the
    false match."""
    views = {track: vs for track, vs in views.items() if vs}
    if not views:
        return {}
    uvv = np.array([m for vs in views.values() for _, m in vs], dtype=float)
    # a panorama frame's views share one mount object: convert each mount once
    mount_matrices: dict[int, np.ndarray] = {}
    for vs in views.values():
        for mount, _ in vs:
            if id(mount) not in mount_matrices:
                mount_matrices[id(mount)] = mount.matrix()
    body_T_cam = np.stack([mount_matrices[id(mount)] for vs in views.values() for mount, _ in vs])
    rots, shifts = body_T_cam[:, :3, :3], body_T_cam[:, :3, 3]
    p_cam = triangulate_rectified(uvv[:, 0], uvv[:, 1], uvv[:, 2], rig.wac, rig.baseline_m)
    usable = np.all(np.isfinite(p_cam), axis=1) & (p_cam[:, 2] > MIN_RANGE_M)
    p_cam[~usable] = [0.0, 0.0, 1.0]  # a placeholder keeping the arithmetic finite; its track comes out None
    cov_cam = triangulation_covariance(p_cam, rig.wac, rig.baseline_m, sigma_px)
    points = np.einsum("nij,nj->ni", rots, p_cam) + shifts
    covs = rots @ cov_cam @ np.transpose(rots, (0, 2, 1))

    # information-weighted mean per track; then each view's agreement with its track's mean
    index = np.repeat(np.arange(len(views)), [len(vs) for vs in views.values()])
    infos = np.linalg.inv(covs)
    info_sum = np.zeros((len(views), 3, 3))
    np.add.at(info_sum, index, infos)
    info_mean = np.zeros((len(views), 3))
    np.add.at(info_mean, index, np.einsum("nij,nj->ni", infos, points))
    cov = np.linalg.inv(info_sum)
    mean = np.einsum("tij,tj->ti", cov, info_mean)
    diff = points - mean[index]
    worst = np.zeros(len(views))
    np.maximum.at(worst, index, np.einsum("ni,nij,nj->n", diff, infos, diff))
    broken = np.zeros(len(views), dtype=bool)
    np.logical_or.at(broken, index, ~usable)
    good = ~broken & (worst <= AGREEMENT_GATE)
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    return {track: SitePoint(mean[i], cov[i]) if good[i] else None for i, track in enumerate(views)}


@dataclass(frozen=True)
class RelativePose:
    """a_T_b between two site poses at the current estimate, with its 6x6 covariance
    ([rotation, translation], GTSAM's tangent space of a_T_b) and, composed from VO steps that
    know theirs, its first-order change with the stereo pair's calibration error (6 x 6, d a_T_b
    / d c in the same tangent space; geometry/calibration_error.py's terms)."""

    a_T_b: gtsam.Pose3
    covariance: np.ndarray
    calibration_sensitivity: np.ndarray | None = None

    @classmethod
    def from_joint(cls, world_T_a: gtsam.Pose3, world_T_b: gtsam.Pose3, joint: np.ndarray) -> RelativePose:
        """From the two poses and their 12x12 joint marginal covariance (a first, then b)."""
        h_a = np.zeros((6, 6), order="F")
        h_b = np.zeros((6, 6), order="F")
        a_T_b = world_T_a.between(world_T_b, h_a, h_b)
        jac = np.hstack([h_a, h_b])
        cov = jac @ joint @ jac.T
        return cls(a_T_b, 0.5 * (cov + cov.T))

    @classmethod
    def compose(cls, steps: list[tuple[gtsam.Pose3, np.ndarray]],
                sensitivities: list[np.ndarray | None] | None = None) -> RelativePose:
        """Along a chain of independent (prev_T_curr, covariance) steps from a to b; with each
        VO step's calibration sensitivity S (Motion.calibration_sensitivity: the step measured
        through a pair off by c is the true one times Expmap(-S c); None: the step knows none),
        the chain's."""
        a_T_b, cov = gtsam.Pose3(), np.zeros((6, 6))
        sensitivity = None if sensitivities is None else np.zeros((6, 6))
        h_chain, h_step = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        for k, (step, step_cov) in enumerate(steps):
            a_T_b = a_T_b.compose(step, h_chain, h_step)
            cov = h_chain @ cov @ h_chain.T + h_step @ step_cov @ h_step.T
            if sensitivity is not None:
                sensitivity = h_chain @ sensitivity
                if sensitivities[k] is not None:
                    sensitivity -= h_step @ sensitivities[k]
        return cls(a_T_b, cov, sensitivity)


def disagreement2(at_a: SitePoint, at_b: SitePoint, relative: RelativePose) -> float:
    """Squared Mahalanobis distance between site a's triangulation and site b's moved into a's
    frame, with both triangulations' and the relative pose's covariances."""
    h_pose = np.zeros((3, 6), order="F")
    h_point = np.zeros((3, 3), order="F")
    predicted = relative.a_T_b.transformFrom(at_b.p_body, h_pose, h_point)
    cov = at_a.cov_body + h_point @ at_b.cov_body @ h_point.T + h_pose @ relative.covariance @ h_pose.T
    diff = at_a.p_body - predicted
    return float(diff @ np.linalg.solve(cov, diff))
