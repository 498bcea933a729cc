"""How close an estimate comes to the Cramer-Rao lower bound of its own factor graph, and
whether its covariance tells the truth about its errors (NEES).

CRLB: the graph's information evaluated at the ground truth (every pose and landmark at its
true value), inverted by iSAM2 with QR (batch Cholesky calls long VO chains indeterminate; see
`graph.smoother`) through the smoother's own window: a stop that left the window is bounded by
the information it had as it left, as its estimate was frozen then. Errors are not aligned: the
start prior fixes the gauge of both the estimate and the bound.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass

import gtsam
import numpy as np

from ..errors import EvaluationError, GraphError
from ..graph import chi2
from ..graph.keys import L, X, subset
from ..graph.smoother import Smoother

POSITION_DOF = 3
NEES_BOUND_99 = float(chi2.quantile(0.99, POSITION_DOF))  # a position's 99 % ellipsoid


class PointsByTrack(Mapping[int, np.ndarray]):
    """Some tracks' true landmark positions, copied out of the truth's array: the bound reads
    rows, not the whole array, which a worker maps and would otherwise keep resident."""

    def __init__(self, tracks: np.ndarray, positions: np.ndarray):
        self.tracks = np.asarray(tracks, dtype=np.int64)  # sorted
        self.positions = np.asarray(positions, dtype=float)

    def __getitem__(self, track: int) -> np.ndarray:
        i = int(np.searchsorted(self.tracks, track))
        if i == len(self.tracks) or self.tracks[i] != track:
            raise KeyError(track)
        return self.positions[i]

    def __len__(self) -> int:
        return len(self.tracks)

    def __iter__(self) -> Iterator[int]:
        return iter(self.tracks.tolist())


def crlb_position_covariances(smoother: Smoother, stops: list[int], world_T_body: np.ndarray,
                              landmarks: Mapping[int, np.ndarray] | np.ndarray,
                              extra: gtsam.Values | None = None) -> np.ndarray:
    """(N, 3, 3) world-frame position covariances of X(stop) from the smoother's graph linearized
    at the truth, through its window: `world_T_body` (N, 4, 4) for `stops`, `landmarks` track ->
    true position (a mapping, or an array indexed by track), `extra` the true values of any
    other variable. The true values are made as the replay inserts its variables, not all at
    once (mission_traverse: 33,589 poses and every landmark a group saw)."""
    at_stop = {k: i for i, k in enumerate(stops)}
    extra = gtsam.Values() if extra is None else extra

    def true_values(keys: list[int]) -> gtsam.Values:
        out = subset(extra, [key for key in keys if extra.exists(key)])
        for key in keys:
            if extra.exists(key):
                continue
            symbol = gtsam.Symbol(key)
            if symbol.chr() == _POSE and symbol.index() in at_stop:
                out.insert(key, gtsam.Pose3(world_T_body[at_stop[symbol.index()]]))
            elif symbol.chr() == _LANDMARK:
                out.insert(key, np.asarray(landmarks[symbol.index()], dtype=float))
            else:
                raise ValueError(f"no true value of {symbol}")
        return out

    try:
        marginals = smoother.marginals_at(true_values, [X(k) for k in stops])
    except GraphError as exc:
        raise EvaluationError(f"CRLB: the graph at ground truth cannot be inverted: {exc}") from None
    rot = world_T_body[:, :3, :3]
    return rot @ np.stack([marginals[X(k)] for k in stops])[:, 3:, 3:] @ rot.transpose(0, 2, 1)


_POSE, _LANDMARK = gtsam.Symbol(X(0)).chr(), gtsam.Symbol(L(0)).chr()


@dataclass(frozen=True)
class Consistency:
    rmse_m: float  # 3-D position, unaligned
    crlb_rms_m: float  # sqrt(mean trace of the CRLB position covariances)
    efficiency: float  # rmse / crlb_rms: 1 is the bound
    anees: float  # mean over poses of e^T P^-1 e / 3, P the estimator's own covariance
    anees_band: tuple[float, float]  # 95 % band for independent poses (see `anees_band`)

    def as_dict(self) -> dict:
        return asdict(self) | {"anees_band": list(self.anees_band)}


def anees_band(samples: int, dof: int = POSITION_DOF, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the mean of `samples` independent chi-square(dof)/dof values."""
    tail = (1 - confidence) / 2
    n = samples * dof
    return float(chi2.quantile(tail, n) / n), float(chi2.quantile(1 - tail, n) / n)


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """e^T P^-1 e per pose, (N,)."""
    return np.einsum("ni,ni->n", errors, np.linalg.solve(covariances, errors[:, :, None])[:, :, 0])


def consistency(estimate: np.ndarray, truth: np.ndarray, estimator_cov: np.ndarray, crlb_cov: np.ndarray
                ) -> Consistency:
    """For one run. Its ANEES band treats the poses as independent, which along a chain they are
    not (errors are correlated), so it is narrower than a fair test: `bench --monte-carlo`
    compares the mean over independent runs instead."""
    errors = estimate - truth
    crlb_rms = float(np.sqrt(np.mean(np.trace(crlb_cov, axis1=1, axis2=2))))
    rmse = float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))
    return Consistency(rmse, crlb_rms, rmse / crlb_rms, float(np.mean(nees(errors, estimator_cov)) / POSITION_DOF),
                       anees_band(len(errors)))


@dataclass(frozen=True)
class NeesAlongRun:
    """Each stop's position NEES against the reference (3 dof): where along a run the covariance
    holds. A right covariance puts 1 % of the samples outside their 99 % ellipsoid. Against the
    truth there is a sample per stop; against GPS fixes (no truth) one per fix, at the stop
    nearest it in time, with the fix's own covariance added."""

    nees: np.ndarray  # (M,), e^T P^-1 e of each sample's position
    vo_inliers: np.ndarray  # (M,) of the VO step into the sample's stop; -1 where there was none
    stop_indices: np.ndarray | None = None  # (M,) the stop of each sample; None: sample k is stop k
    against: str = "truth"  # or "gps"

    LARGEST = 5  # samples listed with the largest NEES

    @property
    def stops(self) -> np.ndarray:
        return np.arange(len(self.nees)) if self.stop_indices is None else self.stop_indices

    @property
    def outside_99_fraction(self) -> float:
        return float(np.mean(self.nees > NEES_BOUND_99))

    @property
    def last(self) -> float:
        return float(self.nees[-1])

    @property
    def anees(self) -> float:
        return float(np.mean(self.nees)) / POSITION_DOF

    def largest(self) -> list[int]:
        """The samples whose NEES is largest, largest first."""
        return [int(k) for k in np.argsort(-self.nees, kind="stable")[:self.LARGEST]]

    def as_dict(self) -> dict:
        entry = {"nees_last": self.last, "nees_outside_99_pct": 100.0 * self.outside_99_fraction,
                 "nees_largest": [{"stop": int(self.stops[k]), "nees": float(self.nees[k]),
                                   "vo_inliers": int(self.vo_inliers[k])} for k in self.largest()]}
        if self.against != "truth":
            entry |= {"nees_against": self.against, "nees_samples": len(self.nees)}
        return entry


def nees_along_run(estimate: np.ndarray, truth: np.ndarray, covariances: np.ndarray,
                   vo_inliers: np.ndarray) -> NeesAlongRun:
    """Positions (N, 3) against the reference's, with the estimator's own (N, 3, 3) covariances."""
    return NeesAlongRun(nees(estimate - truth, covariances), vo_inliers)


def monte_carlo_summary(runs: list[Consistency], nees_last: list[float] | None = None) -> dict:
    """Efficiency and ANEES over independent runs (seeds) of one configuration. Each pose's mean
    NEES over N runs is chi-square(3N)/(3N) when the covariance is right; the mean over poses of
    correlated such values has at most that spread, so that band is the (conservative) test.
    With the runs' last-stop NEES, also their exact test (`last_stop`, last_stop_summary)."""
    n = len(runs)
    efficiency = float(np.sqrt(np.mean([r.rmse_m**2 for r in runs]) / np.mean([r.crlb_rms_m**2 for r in runs])))
    anees = float(np.mean([r.anees for r in runs]))
    band = anees_band(n)
    verdict = covariance_verdict(anees, band)
    return {"runs": n, "efficiency": efficiency, "rmse_m": float(np.sqrt(np.mean([r.rmse_m**2 for r in runs]))),
            "crlb_rms_m": float(np.sqrt(np.mean([r.crlb_rms_m**2 for r in runs]))), "anees": anees,
            "anees_band": list(band), "covariance": verdict} | (
        {} if nees_last is None else {"last_stop": last_stop_summary(nees_last)})


def covariance_verdict(normalized_nees: float, band: tuple[float, float]) -> str:
    if normalized_nees > band[1]:
        return "over-confident"
    return "consistent" if normalized_nees >= band[0] else "under-confident"


def last_stop_summary(nees_last: list[float]) -> dict:
    """The last stop's NEES over independent runs (seeds) of one configuration: each is
    chi-square(3) when the covariance is right and the runs are independent, so their mean / 3
    is chi-square(3N)/(3N) exactly; no correlation along a run widens or narrows the band."""
    n = len(nees_last)
    value = float(np.mean(nees_last)) / POSITION_DOF
    band = anees_band(n)
    return {"runs": n, "nees_last": value, "band": list(band), "covariance": covariance_verdict(value, band)}
