"""Covariance of a planar transform estimated from corresponding noisy points, the dissertation's eqs.
(3.4)-(3.10), and its propagation over a chain of stops, (3.12)-(3.13).

`target = R source + t`. The dissertation's model (3.5) is the 4-parameter one, R = [[a, b], [-b, a]]
with a and b free (a rotation and a scale); `rigid` keeps a^2 + b^2 = 1 (a heading psi with
a = cos psi, b = sin psi), which is what a rover's pose, and our estimator, has. Both point
sets are noisy: the Gauss-Helmert adjustment A V + B Delta = L of (3.6) with
Sigma_DeltaDelta = [B^T (A Sigma A^T)^-1 B]^-1, (3.7).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

TransformModel = Literal["similarity", "rigid"]


def fit_transform(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the similarity that best maps `source` onto `target` (exact when noise-free)."""
    rows = np.zeros((2 * len(source), 4))
    rows[0::2] = np.column_stack([source[:, 0], source[:, 1], np.ones(len(source)), np.zeros(len(source))])
    rows[1::2] = np.column_stack([source[:, 1], -source[:, 0], np.zeros(len(source)), np.ones(len(source))])
    a, b, c, d = np.linalg.lstsq(rows, target.reshape(-1), rcond=None)[0]
    return np.array([[a, b], [-b, a]]), np.array([c, d])


def _parameter_jacobian(rotation: np.ndarray, point: np.ndarray, model: TransformModel) -> np.ndarray:
    """d(R p + t)/d(parameters): (a, b, c, d) for the similarity, (psi, c, d) for the rigid model."""
    x, z = point
    if model == "similarity":
        return np.array([[x, z, 1.0, 0.0], [z, -x, 0.0, 1.0]])
    a, b = rotation[0]  # a = cos psi, b = sin psi; dR/dpsi = [[-b, a], [-a, -b]]
    return np.array([[-b * x + a * z, 1.0, 0.0], [-a * x - b * z, 0.0, 1.0]])


def transform_covariance(source: np.ndarray, source_cov: np.ndarray, target: np.ndarray, target_cov: np.ndarray,
                         model: TransformModel = "similarity") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Sigma_DeltaDelta, R, t) for points (N, 2) with covariances (N, 2, 2), eq. (3.7).

    A is [-R, I] per point (the observation corrections of source and target), so A Sigma A^T is
    block diagonal with blocks target_cov + R source_cov R^T."""
    rotation, translation = fit_transform(source, target)
    if model == "rigid":
        rotation = rotation / np.sqrt(np.linalg.det(rotation))
    information = 0.0
    for p, cov_s, cov_t in zip(source, source_cov, target_cov, strict=True):
        b = _parameter_jacobian(rotation, p, model)
        information = information + b.T @ np.linalg.inv(cov_t + rotation @ cov_s @ rotation.T) @ b
    return np.linalg.inv(information), rotation, translation


def position_covariance(parameter_cov: np.ndarray, rotation: np.ndarray, point: np.ndarray,
                        model: TransformModel = "similarity") -> np.ndarray:
    """Covariance of R p + t for a point p of the source frame (the rover's position), eqs.
    (3.9)-(3.10): C Sigma_DeltaDelta C^T."""
    c = _parameter_jacobian(rotation, np.asarray(point, dtype=float), model)
    return c @ parameter_cov @ c.T


def propagate(steps: list[tuple[np.ndarray, np.ndarray, np.ndarray]], model: TransformModel = "similarity"
              ) -> list[np.ndarray]:
    """Covariances (2x2) of the rover's position at stops 1..n in the frame of stop 0.

    Each step k is (Sigma_DeltaDelta, R, t) of the transform taking stop-k coordinates to stop
    k-1's. The position of stop n is T_1 T_2 ... T_n applied to the origin, (3.13); this is its
    first-order covariance with independent steps (the dissertation writes the result as (3.14),
    Sigma_n = Sigma_DeltaDelta^(n-1), which as printed is a matrix power, not a propagation)."""
    out = []
    for n in range(1, len(steps) + 1):
        cov = np.zeros((2, 2))
        # the stop-n origin seen from each frame k, and the linear part of T_1 ... T_(k-1)
        points = [np.zeros(2)]
        for _, rotation, translation in reversed(steps[1:n]):
            points.append(rotation @ points[-1] + translation)
        points.reverse()  # points[k]: stop n's position in the frame of stop k + 1
        linear = np.eye(2)
        for k in range(n):
            parameter_cov, rotation, _ = steps[k]
            j = linear @ _parameter_jacobian(rotation, points[k], model)
            cov += j @ parameter_cov @ j.T
            linear = linear @ rotation
        out.append(cov)
    return out
