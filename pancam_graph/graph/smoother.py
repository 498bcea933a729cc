"""iSAM2 smoother that also keeps the whole graph for batch polishing and checkpoints."""

from __future__ import annotations

import time

import gtsam
import numpy as np

from ..errors import GraphError


class Smoother:
    """Collect new factors and values, update iSAM2 once, clear: GTSAM's incremental loop.

    Every new pose arrives with a motion factor and every landmark with at least two stereo
    factors, so the graph is always determined. Still, Cholesky declares long VO chains
    without GPS "indeterminate" (denver_trail: at stop 400): the accumulated uncertainty
    (metres) is ~1e6 times the per-step one (millimetres), and forming the Hessian squares
    that ratio past double precision. QR never forms the Hessian; on these graphs it costs
    little (see `pancam-graph bench`).
    """

    def __init__(self, relinearize_threshold: float = 0.05, relinearize_skip: int = 1):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = relinearize_skip
        params.setFactorization("QR")  # see the class docstring
        self.isam = gtsam.ISAM2(params)
        self.graph = gtsam.NonlinearFactorGraph()  # every factor ever added
        self.initial = gtsam.Values()  # every initial value ever added
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self.update_ms: list[float] = []  # wall time of each update
        self.relinearized: list[int] = []  # variables relinearized by each update

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        self._new_factors.add(factor)

    def insert(self, key: int, value) -> None:
        self._new_values.insert(key, value)

    def update(self, context: str = "") -> float:
        """One iSAM2 update with the collected factors; returns its wall time in ms."""
        start = time.perf_counter()
        try:
            result = self.isam.update(self._new_factors, self._new_values)
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 update failed {context}: {exc}") from None
        elapsed = (time.perf_counter() - start) * 1e3
        self.graph.push_back(self._new_factors)
        self.initial.insert(self._new_values)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self.update_ms.append(elapsed)
        self.relinearized.append(result.getVariablesRelinearized())
        return elapsed

    def settle(self, iterations: int = 3) -> None:
        """Extra relinearization passes at the end of a traverse (not counted as per-stop updates)."""
        for _ in range(iterations):
            self.isam.update()

    def pose(self, key: int) -> gtsam.Pose3:
        return self._current(key, gtsam.Values.atPose3, gtsam.ISAM2.calculateEstimatePose3)

    def estimate_double(self, key: int) -> float:
        return float(self._current(key, gtsam.Values.atDouble, gtsam.ISAM2.calculateEstimateDouble))

    def point(self, key: int) -> np.ndarray:
        return self._current(key, gtsam.Values.atPoint3, gtsam.ISAM2.calculateEstimatePoint3)

    def _current(self, key: int, pending_getter, estimate_getter):
        """A variable's value: its initial value if not yet in iSAM2, else the current estimate."""
        if self._new_values.exists(key):
            return pending_getter(self._new_values, key)
        try:
            return estimate_getter(self.isam, key)
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 estimate of {gtsam.Symbol(key).string()} failed: {exc}") from None

    def marginal_covariance(self, key: int) -> np.ndarray:
        """Marginal covariance of a variable from the Bayes tree (tangent space; for a Pose3,
        [rotation, translation] in the body frame)."""
        try:
            return self.isam.marginalCovariance(key)
        except RuntimeError as exc:
            raise GraphError(f"marginal covariance of {gtsam.Symbol(key).string()} failed: {exc}") from None

    def joint_marginal_covariance(self, a: int, b: int) -> np.ndarray:
        """12x12 joint marginal covariance of two variables (a's block first), tangent spaces."""
        try:
            joint = self.isam.jointMarginalCovariance([a, b])
        except RuntimeError as exc:
            names = f"{gtsam.Symbol(a).string()}, {gtsam.Symbol(b).string()}"
            raise GraphError(f"joint marginal covariance of {names} failed: {exc}") from None
        return np.block([[joint.at(a, a), joint.at(a, b)], [joint.at(b, a), joint.at(b, b)]])

    def estimate(self) -> gtsam.Values:
        try:
            return self.isam.calculateEstimate()
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 estimate failed: {exc}") from None

    def batch_polish(self, start: gtsam.Values, max_iterations: int = 50) -> gtsam.Values:
        """Levenberg-Marquardt over the whole graph, started from `start`."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        try:
            return gtsam.LevenbergMarquardtOptimizer(self.graph, start, params).optimize()
        except RuntimeError as exc:
            raise GraphError(f"batch Levenberg-Marquardt failed: {exc}") from None


def poses_array(values: gtsam.Values, keys: list[int]) -> np.ndarray:
    return np.stack([values.atPose3(k).matrix() for k in keys])
