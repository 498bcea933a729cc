"""Stereo VO of the stops ahead of the run, estimated in a worker process.

The localizers of stop k need only stop k's motion, and the VO of the stops after it needs
nothing the localizers compute: on a machine with a second core the VO runs there, a block of
stops at a time, while the localizers work through the stops already estimated. The worker
builds its own StereoVO (GTSAM's stereo calibration does not survive pickling) and sends back
plain VoResults; the run turns them into motions in order, as before.
"""

from __future__ import annotations

import multiprocessing
import os
import uuid
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..errors import FrontendError
from ..geometry.rig import Rig
from ..records import StereoObservations, Traverse
from ..runtime.processes import cores, process_context, start_worker
from .stereo_vo import StereoVO, VoResult

BLOCK_STOPS = 64  # stops per task: enough to hide the pickling, few enough to start at once
MIN_STOPS = 400  # below this, a worker process's start is not paid back


@dataclass(frozen=True)
class VoSetup:
    """What a worker process needs to build the run's StereoVO (GTSAM's stereo calibration does
    not survive pickling): built once per process and setup."""

    rig: Rig
    body_T_nav: np.ndarray
    pixel_sigma: float
    estimator: EstimatorConfig
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @staticmethod
    def of(traverse: Traverse, estimator: EstimatorConfig) -> VoSetup:
        return VoSetup(traverse.rig, traverse.body_T_nav().matrix(), traverse.image_noise_px, estimator)


_worker_vo: dict[str, StereoVO] = {}  # this process's StereoVO per setup token


def estimate_block(setup: VoSetup, pairs: list[tuple[StereoObservations, StereoObservations]]) -> list[VoResult]:
    """The VO of consecutive stereo observations (prev, curr), in a worker process."""
    if setup.token not in _worker_vo:
        _worker_vo.clear()
        _worker_vo[setup.token] = StereoVO.configured(setup.rig, gtsam.Pose3(setup.body_T_nav), setup.pixel_sigma,
                                                      setup.estimator)
    vo = _worker_vo[setup.token]
    return [vo.estimate(prev, curr) for prev, curr in pairs]


def block_pairs(traverse: Traverse, start: int, end: int) -> list[tuple[StereoObservations, StereoObservations]]:
    return [(traverse.stops[k - 1].stereo, traverse.stops[k].stereo) for k in range(start, end)]


class VoAhead:
    """VoResults of stops `first`.. in order, estimated ahead in blocks by one worker process,
    or by the workers of `pool` (which stays open)."""

    def __init__(self, traverse: Traverse, estimator: EstimatorConfig, first: int,
                 pool: ProcessPoolExecutor | None = None):
        self.stops = traverse.stops
        self.next = max(first, 1)
        self.own_pool = pool is None
        if pool is None:
            pool = ProcessPoolExecutor(1, mp_context=process_context(), initializer=start_worker,
                                       initargs=(os.getpid(),))
        self.pool = pool
        setup = VoSetup.of(traverse, estimator)
        self.blocks: deque[tuple[int, Future]] = deque()
        for start in range(self.next, len(self.stops), BLOCK_STOPS):
            end = min(start + BLOCK_STOPS, len(self.stops))
            self.blocks.append((start, self.pool.submit(estimate_block, setup, block_pairs(traverse, start, end))))
        self.ready: deque[VoResult] = deque()

    @staticmethod
    def worth_it(traverse: Traverse, first: int) -> bool:
        """A second core, a long enough way to go, and not inside a daemon (a Dask worker may
        not start processes; a sweep is parallel already)."""
        return (cores() > 1 and len(traverse.stops) - first >= MIN_STOPS
                and not multiprocessing.current_process().daemon)

    def result(self, k: int) -> VoResult:
        """The VO from stop k - 1 to stop k; stops are asked for in order."""
        if k != self.next:
            raise FrontendError(f"VO ahead: stop {k} asked for, stop {self.next} expected")
        if not self.ready:
            start, future = self.blocks.popleft()
            try:
                self.ready.extend(future.result())
            except Exception as exc:  # a crashed worker: name it, nothing else was lost
                raise FrontendError(f"the VO worker failed on stops {start}-{start + BLOCK_STOPS - 1}: "
                                    f"{type(exc).__name__}: {exc}") from None
        self.next += 1
        return self.ready.popleft()

    def close(self) -> None:
        if self.own_pool:
            self.pool.shutdown(wait=False, cancel_futures=True)
