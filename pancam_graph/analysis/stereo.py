"""Stereo triangulation covariance, the dissertation's eqs. (3.1)-(3.3) and (3.11), and error ellipses.

Coordinates are the dissertation's: in the plane of the left camera, X across (right) and Z along the
optical axis (range), both from the left camera's centre; Y (elevation) is held constant, as
in the dissertation. A rectified pair with baseline B and focal length f (pixels) measures x_l and x_r.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import rig
from ..graph import chi2


def triangulation_jacobian(x_m: float, z_m: float, baseline_m: float, focal_px: float) -> np.ndarray:
    """d(X, Z) / d(x_l, x_r), eq. (3.2): [[(B - X) Z, X Z], [-Z^2, Z^2]] / (B f), the planar
    block of the stereo Jacobian the VO front end uses (`rig.triangulation_jacobian`)."""
    return rig.triangulation_jacobian(np.array([[x_m, 0.0, z_m]]), baseline_m, focal_px)[0][np.ix_([0, 2], [0, 1])]


def point_covariance(x_m: float, z_m: float, baseline_m: float, focal_px: float, sigma_left_px: float,
                     sigma_right_px: float | None = None) -> np.ndarray:
    """Covariance (m^2) of the point's (X, Z), eq. (3.3): J diag(sigma_xl^2, sigma_xr^2) J^T."""
    sigma_right_px = sigma_left_px if sigma_right_px is None else sigma_right_px
    j = triangulation_jacobian(x_m, z_m, baseline_m, focal_px)
    return j @ np.diag([sigma_left_px**2, sigma_right_px**2]) @ j.T


def hrc_point_covariance(x_m: float, z_m: float, hrc_baseline_m: float, hrc_focal_px: float, wac_focal_px: float,
                         sigma_px: float) -> np.ndarray:
    """Covariance of (X, Z) from the HRC + left-WAC pair, eq. (3.11).

    The left WAC image is interpolated to the HRC's scale, so the pair is a rectified stereo pair
    with the HRC's focal length and baseline B_h; the interpolated WAC keeps its own angular
    accuracy, so its matching sigma in HRC pixels is sigma * f_hrc / f_wac (the dissertation's "about 9
    times"; 7.1 for ExoMars' 580 and 82 urad/px)."""
    return point_covariance(x_m, z_m, hrc_baseline_m, hrc_focal_px, sigma_px * hrc_focal_px / wac_focal_px, sigma_px)


def rotate_covariance(cov: np.ndarray, angle_rad: float) -> np.ndarray:
    """The covariance of a planar (X, Z) vector after rotating the vector by angle (X towards Z
    positive: a point at bearing `angle` right of the axis has X = r sin, Z = r cos)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    rot = np.array([[c, s], [-s, c]])
    return rot @ cov @ rot.T


@dataclass(frozen=True)
class Ellipse:
    """A confidence ellipse in the (X, Z) plane."""

    semi_major_m: float
    semi_minor_m: float
    angle_rad: float  # of the major axis, from +X towards +Z
    confidence: float


def error_ellipse(cov: np.ndarray, confidence: float = 0.95) -> Ellipse:
    """The region holding `confidence` of a 2-D Gaussian: semi-axes sqrt(chi2_2(p) * eigenvalue)."""
    values, vectors = np.linalg.eigh(np.asarray(cov, dtype=float))
    scale = chi2.quantile(confidence, 2)
    major = vectors[:, 1]
    return Ellipse(float(np.sqrt(scale * values[1])), float(np.sqrt(scale * max(values[0], 0.0))),
                   float(np.arctan2(major[1], major[0])), confidence)
