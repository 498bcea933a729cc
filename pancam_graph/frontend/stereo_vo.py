"""Stereo visual odometry from matched stereo observations of two consecutive stops.

Method: triangulate the previous stop's matches (the dissertation's eq. 2.28), estimate the motion by
3-D to 2-D PnP with RANSAC (OpenCV), then refine it by a bundle adjustment over the two
stops (two_stop_adjustment.py: the system of GTSAM's stereo factors, previous pose held
fixed) whose marginal gives the 6x6 covariance of the relative pose. Outliers left after
RANSAC are removed by a chi-square test on the bundle-adjustment residuals.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass

import cv2
import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..geometry.rig import Rig, triangulate_rectified, triangulation_covariance
from ..graph import chi2
from ..records import StereoObservations, Traverse
from .two_stop_adjustment import StereoIntrinsics, adjust_two_stops

_CHI2_6DOF_99 = chi2.quantile(0.99, 6)  # a point's two stereo residuals (2 x 3 px components): outlier gate
_CHI2_3DOF_999 = chi2.quantile(0.999, 3)  # a point's two triangulations (3-D difference): re-admission gate
# A step whose two-stop adjustment cannot be solved (a landmark placed where the system is
# nearly singular) is a VO failure like any other: the motion bridges it.
_INDETERMINATE = "two-stop adjustment indeterminate"


@dataclass(frozen=True)
class VoResult:
    """prev_T_curr of the rover body and its covariance ([rotation, translation], current frame);
    its sensitivity to the pair's calibration error (TwoStopSolution.calibration_sensitivity)."""

    ok: bool
    prev_T_curr: gtsam.Pose3 | None
    covariance: np.ndarray | None
    matches: int
    inliers: int
    reason: str = ""
    calibration_sensitivity: np.ndarray | None = None


@dataclass
class StereoVO:
    """Two-stop stereo VO of a pair mounted at body_T_left. Every setting is the estimator
    configuration's (`configured`): written once, there."""

    rig: Rig
    body_T_left: gtsam.Pose3
    pixel_sigma: float
    _: KW_ONLY
    min_inliers: int
    ransac_px: float
    max_step_m: float
    pnp_iterations: int
    pnp_confidence: float
    max_range_m: float
    translation_floor: float
    rotation_floor_rad_per_m: float
    sigma_scale: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        self.left_T_body = self.body_T_left.inverse()
        self.intrinsics = StereoIntrinsics.of(self.rig.stereo_calibration())
        self.K = self.rig.wac.matrix()
        self.ransac_px = max(self.ransac_px, 4.0 * self.pixel_sigma)

    @classmethod
    def for_traverse(cls, traverse: Traverse, estimator: EstimatorConfig | None = None) -> StereoVO:
        """The VO of a traverse's navigation stereo pair (pan 0, traverse tilt)."""
        return cls.configured(traverse.rig, traverse.body_T_nav(), traverse.image_noise_px, estimator)

    @classmethod
    def configured(cls, rig: Rig, body_T_left: gtsam.Pose3, pixel_sigma: float,
                   estimator: EstimatorConfig | None = None) -> StereoVO:
        """The VO of a stereo pair mounted at body_T_left, with the estimator's settings."""
        est = estimator or EstimatorConfig()
        return cls(
            rig, body_T_left, pixel_sigma,
            min_inliers=est.vo_min_inliers, ransac_px=est.vo_ransac_px, max_step_m=est.vo_max_step_m,
            pnp_iterations=est.vo_pnp_iterations, pnp_confidence=est.vo_pnp_confidence,
            max_range_m=est.vo_max_range_m, translation_floor=est.vo_translation_floor,
            rotation_floor_rad_per_m=np.deg2rad(est.vo_rotation_floor_deg_per_m),
            sigma_scale=est.vo_sigma_scale,
        )

    def estimate(self, prev: StereoObservations, curr: StereoObservations) -> VoResult:
        _, ip, ic = np.intersect1d(prev.track_ids, curr.track_ids, assume_unique=True, return_indices=True)
        matches = len(ip)
        if matches < self.min_inliers:
            return VoResult(False, None, None, matches, 0, f"{matches} matches < {self.min_inliers}")
        a, b = prev.uvv[ip], curr.uvv[ic]
        p_prev = triangulate_rectified(a[:, 0], a[:, 1], a[:, 2], self.rig.wac, self.rig.baseline_m)
        usable = np.isfinite(p_prev[:, 2]) & (p_prev[:, 2] > 0.5) & (p_prev[:, 2] < self.max_range_m)
        usable &= b[:, 0] > b[:, 1]
        a, b, p_prev = a[usable], b[usable], p_prev[usable]
        if len(a) < self.min_inliers:
            return VoResult(False, None, None, matches, 0, "too few matches with positive disparity")

        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            p_prev, b[:, [0, 2]].copy(), self.K, None, iterationsCount=self.pnp_iterations,
            reprojectionError=self.ransac_px, confidence=self.pnp_confidence, flags=cv2.SOLVEPNP_EPNP,
        )
        if not found or inliers is None or len(inliers) < self.min_inliers:
            n = 0 if inliers is None else len(inliers)
            return VoResult(False, None, None, matches, n, f"PnP RANSAC found {n} inliers")
        inl = inliers.ravel()
        rot, _ = cv2.Rodrigues(rvec)
        curr_T_prev_cam = gtsam.Pose3(gtsam.Rot3(rot), tvec.ravel())
        guess = self.body_T_left.compose(curr_T_prev_cam.inverse()).compose(self.left_T_body)

        pose, _, keep, _ = self._bundle_adjust(a[inl], b[inl], p_prev[inl], guess, covariance=False)
        if pose is None:
            return VoResult(False, None, None, matches, len(inl), _INDETERMINATE)
        if keep.sum() < self.min_inliers:
            return VoResult(False, None, None, matches, int(keep.sum()), "too few inliers after BA")
        # RANSAC judged the matches by reprojecting the previous triangulation, whose range error
        # grows with range squared: it rejects most distant features however good they are. Judge
        # every match again at the refined pose, by how well its two triangulations agree given
        # their covariances, and re-solve with all that pass (the dissertation's error model, eq. 3.3).
        # A re-admitted mismatch can still wreck the re-solve (one with a fraction of a pixel of
        # disparity now, whose range error hides it): then the matches the first solve kept.
        agree = self._consistent(a, b, p_prev, pose)
        first = inl[keep]
        for inl in ([np.flatnonzero(agree), first] if agree.sum() >= keep.sum() else [first]):
            refined, cov, keep, sensitivity = self._bundle_adjust(a[inl], b[inl], p_prev[inl], pose)
            if refined is not None and keep.sum() >= self.min_inliers:
                break
        if refined is None:
            return VoResult(False, None, None, matches, len(inl), _INDETERMINATE)
        if keep.sum() < self.min_inliers:
            return VoResult(False, None, None, matches, int(keep.sum()), "too few inliers after BA")
        pose = refined
        if keep.sum() < len(keep):
            pose, cov, _, sensitivity = self._bundle_adjust(a[inl][keep], b[inl][keep], p_prev[inl][keep], pose)
            if pose is None:
                return VoResult(False, None, None, matches, int(keep.sum()), _INDETERMINATE)
        step = float(np.linalg.norm(pose.translation()))
        if step > self.max_step_m:
            return VoResult(False, None, None, matches, int(keep.sum()), f"implausible step {step:.1f} m")
        return VoResult(True, pose, self._with_floor(cov, step), matches, int(keep.sum()),
                        calibration_sensitivity=sensitivity)

    def _with_floor(self, cov: np.ndarray, step_m: float) -> np.ndarray:
        """The two-stop adjustment's covariance plus what white pixel noise does not explain on
        real images (calibration residuals, errors correlated along a track): independent
        rotation and translation errors in proportion to the step (EstimatorConfig's
        vo_rotation_floor_deg_per_m and vo_translation_floor; zero in simulation), its sigmas then
        scaled by what errors correlated from step to step add over a chain (vo_sigma_scale)."""
        if self.translation_floor or self.rotation_floor_rad_per_m:
            floor = np.r_[np.full(3, self.rotation_floor_rad_per_m), np.full(3, self.translation_floor)] * step_m
            cov = cov + np.diag(floor**2)
        if self.sigma_scale is not None:
            cov = cov * np.outer(self.sigma_scale, self.sigma_scale)
        return cov

    def _consistent(self, a, b, p_prev_cam, pose: gtsam.Pose3) -> np.ndarray:
        """Matches whose current triangulation, moved into the previous camera frame by `pose`,
        agrees with the previous one: squared Mahalanobis distance under the 3-dof gate."""
        cam, base = self.rig.wac, self.rig.baseline_m
        prev_T_curr_cam = self.left_T_body.compose(pose).compose(self.body_T_left)
        rot = prev_T_curr_cam.rotation().matrix()
        p_curr_cam = triangulate_rectified(b[:, 0], b[:, 1], b[:, 2], cam, base)
        p_curr = p_curr_cam @ rot.T + prev_T_curr_cam.translation()
        cov = (triangulation_covariance(p_prev_cam, cam, base, self.pixel_sigma)
               + rot @ triangulation_covariance(p_curr_cam, cam, base, self.pixel_sigma) @ rot.T)
        diff = p_curr - p_prev_cam
        ok = np.all(np.isfinite(diff), axis=1)
        d2 = np.full(len(diff), np.inf)
        d2[ok] = np.einsum("ni,ni->n", diff[ok], np.linalg.solve(cov[ok], diff[ok][:, :, None])[:, :, 0])
        return d2 < _CHI2_3DOF_999

    def _bundle_adjust(self, a, b, p_prev_cam, guess: gtsam.Pose3, covariance: bool = True):
        """(pose, its 6x6 covariance, which matches pass the outlier gate, its 6x6 calibration
        sensitivity), the two matrices None without `covariance`; all None when the two-stop
        system is indeterminate."""
        solution = adjust_two_stops(a, b, p_prev_cam, guess, self.intrinsics, self.body_T_left, self.pixel_sigma,
                                    covariance)
        if solution is None:
            return None, None, None, None
        return (solution.prev_T_curr, solution.covariance, solution.point_chi2 < _CHI2_6DOF_99,
                solution.calibration_sensitivity)
