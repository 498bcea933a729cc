"""The motion between consecutive stops: stereo VO, or a bridge when VO fails.

Never zero motion (what broke the dissertation's field result): dead reckoning with its own
covariance when the rover has it, otherwise the previous motion with a wide covariance.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..records import DeadReckoning, SlipPrior, Stop, Traverse
from .stereo_vo import StereoVO, VoResult

# Without any dead reckoning the bridge only says "the rover moved about as before":
# 2 m per axis, 5 deg roll/pitch and 60 deg heading (1 sigma).
_WIDE_SIGMAS = np.array([np.deg2rad(5.0), np.deg2rad(5.0), np.deg2rad(60.0), 2.0, 2.0, 2.0])


@dataclass(frozen=True)
class Motion:
    prev_T_curr: gtsam.Pose3
    covariance: np.ndarray  # [rotation, translation] in the current body frame
    source: Literal["vo", "dead_reckoning", "constant_velocity"]
    vo_inliers: int
    vo_failure: str = ""
    # The raw odometry increment behind a dead-reckoning motion: the wheel-slip kind builds its
    # own factor from it (prev_T_curr above already has the expected slip taken out).
    odometry: DeadReckoning | None = None
    # A VO motion's first-order change with the stereo pair's calibration error (6 x 6, see
    # TwoStopSolution): the stereo_calibration kind measures the step again with its estimate.
    calibration_sensitivity: np.ndarray | None = None

    @property
    def bridged(self) -> bool:
        return self.source != "vo"


_SOURCES = ("vo", "dead_reckoning", "constant_velocity")


class Motions:
    """Every stop's motion from the previous one (None for the first) as columns of numbers,
    appended a stop at a time and read back as `Motion`s (a list of `Motion` objects costs
    kilobytes a stop): 84 numbers and 3 integers, in blocks of `BLOCK` stops (a large array
    of a group's inputs is mapped by its worker, not copied: side_by_side.Handover)."""

    BLOCK = 4096
    # prev_T_curr's 3x4 [R | t] row by row, the 6x6 covariance, the 6x6 calibration sensitivity (NaN: none)
    _WIDTH = 12 + 36 + 36

    def __init__(self, motions: Iterable[Motion | None] = ()):
        self._numbers: list[np.ndarray] = []  # (BLOCK, _WIDTH) float
        self._codes: list[np.ndarray] = []  # (BLOCK, 3) int: source (-1: none), VO inliers, failure
        self._failures: list[str] = [""]  # the VO's reasons for failing, by index
        self._odometry: list[DeadReckoning | None] = []  # the stops' own records, not copies
        self._n = 0
        self.extend(motions)

    def __len__(self) -> int:
        return self._n

    def append(self, motion: Motion | None) -> None:
        block, i = divmod(self._n, self.BLOCK)
        if block == len(self._numbers):
            self._numbers.append(self._block(self._WIDTH, float))
            self._codes.append(self._block(3, np.int64))
        elif not self._numbers[block].flags.writeable or len(self._numbers[block]) < self.BLOCK:
            # read back (mapped from a file, or the last, short, block of a pickle): a block of its own
            self._numbers[block] = self._block(self._WIDTH, float, self._numbers[block])
            self._codes[block] = self._block(3, np.int64, self._codes[block])
        if motion is None:
            self._codes[block][i] = (-1, 0, 0)
            self._odometry.append(None)
        else:
            if motion.vo_failure not in self._failures:
                self._failures.append(motion.vo_failure)
            self._numbers[block][i, :12] = motion.prev_T_curr.matrix()[:3].ravel()
            self._numbers[block][i, 12:48] = np.asarray(motion.covariance).ravel()
            sensitivity = motion.calibration_sensitivity
            self._numbers[block][i, 48:] = np.nan if sensitivity is None else np.asarray(sensitivity).ravel()
            self._codes[block][i] = (_SOURCES.index(motion.source), motion.vo_inliers,
                                     self._failures.index(motion.vo_failure))
            self._odometry.append(motion.odometry)
        self._n += 1

    def _block(self, width: int, dtype, start: np.ndarray | None = None) -> np.ndarray:
        """A block of `BLOCK` rows, beginning with `start`'s."""
        block = np.zeros((self.BLOCK, width), dtype=dtype)
        if start is not None:
            block[:len(start)] = start
        return block

    def extend(self, motions: Iterable[Motion | None]) -> None:
        for motion in motions:
            self.append(motion)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self._n))]
        if k < 0:
            k += self._n
        if not 0 <= k < self._n:
            raise IndexError(f"motion {k} of {self._n}")
        block, i = divmod(k, self.BLOCK)
        source, inliers, failure = self._codes[block][i].tolist()
        if source < 0:
            return None
        numbers = self._numbers[block][i]
        pose = np.eye(4)
        pose[:3] = numbers[:12].reshape(3, 4)
        sensitivity = numbers[48:].reshape(6, 6)
        return Motion(gtsam.Pose3(pose), numbers[12:48].reshape(6, 6).copy(), _SOURCES[source], inliers,
                      self._failures[failure], self._odometry[k],
                      sensitivity.copy() if np.all(np.isfinite(sensitivity)) else None)

    def __iter__(self) -> Iterator[Motion | None]:
        for k in range(self._n):
            yield self[k]

    def vo_inliers(self) -> np.ndarray:
        """(N,) the VO's inliers at each stop; -1 where there is no motion (the first stop)."""
        codes = self._columns()[1]
        return np.where(codes[:, 0] < 0, -1, codes[:, 1])

    def _columns(self) -> tuple[np.ndarray, np.ndarray]:
        if not self._n:
            return np.zeros((0, self._WIDTH)), np.zeros((0, 3), dtype=np.int64)
        return np.concatenate(self._numbers)[:self._n], np.concatenate(self._codes)[:self._n]

    def __getstate__(self) -> dict:
        numbers, codes = self._columns()
        return {"numbers": numbers, "codes": codes, "failures": self._failures, "odometry": self._odometry}

    def __setstate__(self, state: dict) -> None:
        numbers, codes = state["numbers"], state["codes"]
        self._n = len(codes)
        self._failures, self._odometry = state["failures"], state["odometry"]
        # views of what was read (a mapped array stays mapped until a block is written to: append)
        self._numbers = [numbers[b:b + self.BLOCK] for b in range(0, self._n, self.BLOCK)]
        self._codes = [codes[b:b + self.BLOCK] for b in range(0, self._n, self.BLOCK)]


@dataclass(frozen=True)
class VoMotions:
    """Every stop's motion from the previous one (None for the first), estimated once with this
    estimator configuration: a source that needed them (the site tie points' predictions) hands
    them to the run, which estimates them again only under another configuration."""

    estimator: EstimatorConfig
    motions: tuple[Motion | None, ...]
    seconds: float = 0.0  # what estimating them took

    @staticmethod
    def estimate(traverse: Traverse, estimator: EstimatorConfig) -> VoMotions:
        start = time.perf_counter()
        vo = StereoVO.for_traverse(traverse, estimator)
        motions: list[Motion | None] = [None]
        for k in range(1, len(traverse.stops)):
            motions.append(motion_between(vo, traverse.stops[k - 1], traverse.stops[k], motions[-1],
                                          traverse.wheel_slip))
        return VoMotions(estimator, tuple(motions), time.perf_counter() - start)


def motion_between(vo: StereoVO, prev: Stop, curr: Stop, last: Motion | None, slip: SlipPrior) -> Motion:
    """Stereo VO, bridged by dead reckoning (or constant velocity) where VO fails."""
    return motion_from(vo.estimate(prev.stereo, curr.stereo), curr, last, slip)


def motion_from(result: VoResult, curr: Stop, last: Motion | None, slip: SlipPrior) -> Motion:
    """The VO's motion to stop `curr`, bridged where it failed."""
    if result.ok:
        return Motion(result.prev_T_curr, result.covariance, "vo", result.inliers,
                      calibration_sensitivity=result.calibration_sensitivity)
    return dead_reckoning_motion(curr, last, slip, result.inliers, result.reason)


def dead_reckoning_motion(curr: Stop, last: Motion | None, slip: SlipPrior, vo_inliers: int = 0,
                          vo_failure: str = "") -> Motion:
    """The stop's wheel odometry + IMU increment with the expected slip taken out, and its own
    covariance widened along the drive by the slip's uncertainty (as if it were independent per
    step, which it is not: over many steps only the wheel-slip kind is honest); constant velocity
    with a wide covariance when the stop has none."""
    if curr.dead_reckoning is not None:
        dr = curr.dead_reckoning
        t = dr.prev_T_curr[:3, 3]
        corrected = gtsam.Pose3(gtsam.Rot3(dr.prev_T_curr[:3, :3]), t / (1.0 + slip.mean))
        # translation sigma along the drive, expressed in the current body frame (GTSAM's)
        along = dr.prev_T_curr[:3, :3].T @ t / (1.0 + slip.mean) * slip.sigma
        covariance = dr.covariance.copy()
        covariance[3:, 3:] += np.outer(along, along)
        return Motion(corrected, covariance, "dead_reckoning", vo_inliers, vo_failure, odometry=dr)
    guess = last.prev_T_curr if last is not None else gtsam.Pose3()
    return Motion(guess, np.diag(_WIDE_SIGMAS**2), "constant_velocity", vo_inliers, vo_failure)
