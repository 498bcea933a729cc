"""Named noise models with units."""

from __future__ import annotations

import math

import gtsam
import numpy as np

from ..errors import GraphError
from . import chi2

_KERNELS = {
    "huber": gtsam.noiseModel.mEstimator.Huber.Create,
    "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create,
}


def robust(kind: str, base: gtsam.noiseModel.Base, k: float | None) -> gtsam.noiseModel.Base:
    """Wrap `base` in an M-estimator ('huber', 'cauchy') with threshold `k` sigmas (the estimator's
    huber_k or cauchy_k) of one dimension, or return it ('none')."""
    if kind == "none":
        return base
    if k is None:
        raise GraphError(f"a {kind} kernel needs its threshold k")
    return gtsam.noiseModel.Robust.Create(_KERNELS[kind](norm_threshold(k, base.dim())), base)


def norm_threshold(k: float, dim: int) -> float:
    """The threshold on a `dim`-dof whitened residual's norm that a Gaussian inlier passes as often
    as it passes `k` in one dimension. GTSAM's Robust model applies its kernel to the whole
    residual's norm, and a 3-dof inlier's norm exceeds 1.345 61 % of the time (docs/design.md,
    section 5): k itself would down-weight most good stereo ties, GPS fixes and projections."""
    if dim == 1:
        return k
    return float(np.sqrt(chi2.quantile(math.erf(k / math.sqrt(2.0)), dim)))


def stereo_pixels(sigma_px: float) -> gtsam.noiseModel.Base:
    """(u_left, u_right, v) measurement noise in pixels."""
    return gtsam.noiseModel.Isotropic.Sigma(3, sigma_px)


_BOTH_EYES_U = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # what the matcher's error moves


def stereo_tie(sigma_px: float, tie_sigma_px: float) -> gtsam.noiseModel.Base:
    """(u_left, u_right, v) noise of a tie's stereo view at the later of two sites: the pixel
    noise of each of the three and the matcher's error (`tie_sigma_px` per axis), which moves
    both eyes' pixels alike: it blurs where the site sees the landmark, not its disparity.
    Weighted as pixel noise alone, the two sites' relative pose came out over-confident (NEES
    13.6-18 of 6 at 50 m; tests/graph/test_tie_matching.py)."""
    if tie_sigma_px == 0.0:
        return stereo_pixels(sigma_px)
    return gtsam.noiseModel.Gaussian.Covariance(stereo_tie_covariance(sigma_px, tie_sigma_px))


def stereo_tie_covariance(sigma_px: float, tie_sigma_px: float | np.ndarray) -> np.ndarray:
    """stereo_tie's covariance (px^2): (3, 3), or (N, 3, 3) for N matcher's errors."""
    tie_variance = np.asarray(tie_sigma_px, dtype=float) ** 2
    return sigma_px**2 * np.eye(3) + tie_variance[..., None, None] * _BOTH_EYES_U



def image_pixels(sigma_px: float) -> gtsam.noiseModel.Base:
    """(u, v) measurement noise in pixels."""
    return gtsam.noiseModel.Isotropic.Sigma(2, sigma_px)


def pose_sigmas(rot_rad: np.ndarray, pos_m: np.ndarray) -> gtsam.noiseModel.Base:
    """Pose noise: rotation sigmas (rad) then translation sigmas (m), GTSAM order."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.concatenate([rot_rad, pos_m]))


def pose_covariance(cov: np.ndarray) -> gtsam.noiseModel.Base:
    """A full 6x6 pose covariance ([rotation, translation], rad^2 / m^2)."""
    cov = 0.5 * (cov + cov.T)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)) or np.linalg.eigvalsh(cov).min() <= 0:
        raise GraphError("pose covariance must be a finite, positive-definite 6x6 matrix")
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def landmark_anchor(range_m: float, sigma_m: float = 3.0) -> gtsam.noiseModel.Base:
    """Bearing (rad, two components) and range (m) noise of a landmark anchor: `sigma_m` along and
    across the line of sight. Along it, that is 3 % of one WAC stereo view's information at 40 m
    (0.56 m range sigma at 0.3 px) and less nearer; across it, far less. So it does not bias the
    estimate; it keeps the landmark's block non-singular if a Gauss-Newton step carries it
    behind the cameras, where stereo factors give zero Jacobians (without it a run can diverge).

    It must be relative to the observing site: a world-frame prior at the first triangulation
    feeds the site's drifted position back in as if it were news. About 150 new landmarks per
    site, each with a 3 m world prior, carry the information of a 0.24 m prior on where VO had
    put the site, and the configuration becomes over-confident (docs/results.md, "What made `vo_sites`
    over-confident")."""
    bearing_rad = sigma_m / max(range_m, sigma_m)
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([bearing_rad, bearing_rad, sigma_m]))


def gps_position(sigma_horizontal_m: float, sigma_vertical_m: float) -> gtsam.noiseModel.Base:
    """ENU position noise of a GPS fix in metres."""
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([sigma_horizontal_m, sigma_horizontal_m, sigma_vertical_m])
    )
