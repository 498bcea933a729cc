"""One group of configurations over a traverse: their localizers fed stop by stop, with
checkpoints, then each evaluated against the reference, the bound (CRLB), the GPS fixes and
the held-out fixes. A run in one process is one group; side by side, each process runs one."""

from __future__ import annotations

import gc
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config import EstimatorConfig
from ..errors import GraphError
from ..evaluation.consistency import PointsByTrack, consistency, crlb_position_covariances, nees_along_run
from ..evaluation.gps_check import evaluate_against_gps, holdout_score, nees_against_gps
from ..evaluation.metrics import compare
from ..frontend.motion import Motion, Motions, VoMotions, dead_reckoning_motion, motion_between, motion_from
from ..frontend.stereo_vo import StereoVO
from ..frontend.vo_ahead import VoAhead
from ..kinds import absolute
from ..records import GpsFix, GroundTruth, Stop, Traverse
from ..runtime.memory import release_memory, settle_garbage_collector
from ..runtime.processes import release_mapped_pages
from .housekeeping import Housekeeping, sample_memory
from .listener import NullListener, RunListener
from .localizer import Localizer, Snapshot
from .results import ConfigurationResult, ProcessUse, RunOptions
from .state import Checkpoints, RunState
from .step_table import StepTable
from .stop_records import StopRecords

ProgressCallback = Callable[[str, int, int], None]


@dataclass(frozen=True)
class GroupJob:
    """What a group of configurations needs to run: the traverse and its truth, the estimator,
    the run options and the configurations (name -> kinds)."""

    traverse: Traverse
    truth: GroundTruth | None
    estimator: EstimatorConfig
    seed: int
    options: RunOptions
    held_out: tuple[GpsFix, ...]
    configs: dict[str, list[str]]


@dataclass
class GroupOutcome:
    """A group's configurations evaluated, the motions they were fed, and what the process
    that ran them used."""

    results: dict[str, ConfigurationResult]
    motions: Motions
    vo_s: float
    process: ProcessUse


def localize_group(job: GroupJob, state: RunState | None, known: VoMotions | None, save: Checkpoints | None,
              progress: ProgressCallback | None, listener: RunListener | None, start: float,
              label: str = "run", records: StopRecords | None = None) -> GroupOutcome:
    """A group's configurations stop by stop in this process, then evaluated. Motions the
    state does not have are estimated as the stops come (`known`: a source's; else the VO,
    ahead in a second process on long traverses when the options allow one). `records`: the
    stops' image records, when the traverse's stops come without them (a worker's)."""
    began, began_cpu = time.perf_counter(), time.process_time()
    traverse, slip = job.traverse, job.traverse.wheel_slip
    state = state or new_state(job)
    if save is not None:
        for name, localizer in state.localizers.items():
            localizer.smoother.log.keep_in(save.log_folder(name))
    listener = listener or NullListener()
    n = len(traverse.stops)
    any_vo = any(loc.uses_vo for loc in state.localizers.values())
    needs_vo = any_vo and len(state.motions) < n
    if known is not None and state.next_stop == 0 and needs_vo:
        state.vo_s = known.seconds
    ahead = vo = None
    if needs_vo and known is None:
        if job.options.processes > 1 and VoAhead.worth_it(traverse, len(state.motions)):
            ahead = VoAhead(traverse, job.estimator, len(state.motions))
        else:
            vo = StereoVO.for_traverse(traverse, job.estimator)

    def vo_motion(k: int, last: Motion | None) -> Motion:
        if known is not None:
            return known.motions[k]
        if ahead is not None:  # the wait for the worker, not its work, is timed
            return motion_from(ahead.result(k), traverse.stops[k], last, slip)
        return motion_between(vo, traverse.stops[k - 1], traverse.stops[k], last, slip)

    listener.start(traverse, job.truth, state.localizers)
    settle_garbage_collector()
    housekeeping = Housekeeping(state, n, save, listener, progress, start)
    try:
        _step_through(traverse, state, MotionFeed(traverse, state, vo_motion if any_vo else None),
                      [listener, housekeeping], records)
    finally:
        gc.unfreeze()
        if ahead is not None:
            ahead.close()
    results = {}
    inliers = state.motions.vo_inliers()  # one motion per stop
    # every configuration's estimate first, each solver let go as it is taken: the bounds' replays
    # then come one at a time on top of none
    finished = {}
    for name, localizer in state.localizers.items():
        if progress is not None:
            progress(f"finishing {name}", 0, 1)
        finished[name] = _finish(job, localizer)
    for name in list(state.localizers):
        localizer = state.localizers.pop(name)
        results[name] = _configuration_result(job, name, localizer, finished.pop(name), state.steps[name], progress,
                                              inliers if localizer.uses_vo else np.full(n, -1))
        # its graphs are no more use: their memory goes to the next one's bound, freed at once
        # (closed: no cycle left, so no garbage collection, which walks the whole process)
        localizer.close()
        del localizer
        release_memory(collect_cycles=False)
    sample_memory(state, n - 1, last=True)
    use = ProcessUse(label, os.getpid(), tuple(results), time.perf_counter() - began,
                     time.process_time() - began_cpu, state.memory_mb, state.peak_pss_mb or None)
    return GroupOutcome(results, state.motions, state.vo_s, use)


def new_state(job: GroupJob) -> RunState:
    localizers = {name: Localizer(job.traverse, kinds, job.estimator, seed=job.seed)
                  for name, kinds in job.configs.items()}
    return RunState(0, localizers, Motions([None]), Motions([None]), {name: StepTable() for name in localizers})


class MotionFeed:
    """Each stop's motions for a group's localizers: the VO's (estimated as the stops come by
    `vo_motion`, unless the state has them) and dead reckoning's, kept only where a
    configuration reads them (a mission's motions are tens of MB)."""

    def __init__(self, traverse: Traverse, state: RunState, vo_motion: Callable[[int, Motion | None], Motion] | None):
        self.traverse, self.state, self.vo_motion = traverse, state, vo_motion
        self.needs_dead_reckoning = vo_motion is None or not all(loc.uses_vo for loc in state.localizers.values())

    def at(self, k: int, stop: Stop) -> tuple[Motion | None, Motion | None]:
        """(the VO's motion, dead reckoning's) from stop k - 1 to stop k; (None, None) at stop 0."""
        motions, dr_motions = self.state.motions, self.state.dr_motions
        if self.needs_dead_reckoning and k > 0 and len(dr_motions) <= k:
            dr_motions.append(dead_reckoning_motion(stop, dr_motions[-1], self.traverse.wheel_slip))
        if k > 0 and len(motions) <= k:
            t0 = time.perf_counter()
            motions.append(self.vo_motion(k, motions[-1]) if self.vo_motion is not None else dr_motions[k])
            self.state.vo_s += time.perf_counter() - t0
        return motions[k], dr_motions[k] if self.needs_dead_reckoning else None


def _step_through(traverse: Traverse, state: RunState, feed: MotionFeed, listeners: list[RunListener],
                  records: StopRecords | None = None) -> None:
    """The state's localizers fed every stop from `state.next_stop` on: each stop's motion in,
    each localizer's step, the listeners told."""
    for k in range(state.next_stop, len(traverse.stops)):
        stop = traverse.stops[k] if records is None else records.attach(k, traverse.stops[k])
        motion, dead_reckoning = feed.at(k, stop)
        now = {}
        for name, localizer in state.localizers.items():
            try:
                now[name] = localizer.step(stop, motion if localizer.uses_vo else dead_reckoning)
            except GraphError as exc:  # which of the group's configurations it was
                raise GraphError(f"{name}: {exc}") from None
            except RuntimeError as exc:  # GTSAM's, from a call outside the smoother's update
                raise GraphError(f"{name}: at stop {k}: {exc}") from exc
        for listener in listeners:
            listener.step(stop, motion, now)
    state.next_stop = len(traverse.stops)


@dataclass(frozen=True)
class Finished:
    """What a configuration's results take from its live solver."""

    final: Snapshot
    covariance: np.ndarray  # (N, 3, 3) position covariances, world frame
    counters: dict  # the kinds' counters and their own variables against the truth


def _finish(job: GroupJob, localizer: Localizer) -> Finished:
    """The final estimate, its covariances and the kinds' variables against the truth; then the
    solver is let go (Smoother.release_solver)."""
    localizer.finish()
    final = localizer.final(batch=job.options.batch)
    covariance = localizer.position_covariances()
    counters = {**localizer.counters(), **(localizer.against_truth(job.truth) if job.truth is not None else {})}
    localizer.smoother.release_solver()
    return Finished(final, covariance, counters)


def _configuration_result(job: GroupJob, name: str, localizer: Localizer, finished: Finished, steps: StepTable,
                          progress: ProgressCallback | None, vo_inliers: np.ndarray) -> ConfigurationResult:
    """A configuration's final estimate, its covariances, and its metrics against the
    reference (each stop's NEES too), the bound (CRLB) and GPS."""
    traverse, truth = job.traverse, job.truth
    final, covariance = finished.final, finished.covariance
    poses = final.world_T_body
    alignment = "none" if absolute(localizer.kind_names) else "se3"  # in the world frame as it stands
    metrics = consistency_result = along = None
    if truth is not None:
        metrics = compare(poses[:, :3, 3], truth.positions, alignment, poses, truth.world_T_body)
        along = nees_along_run(poses[:, :3, 3], truth.positions, covariance, vo_inliers)
        extra = localizer.true_values(truth)
        tracks = np.array(sorted(localizer.landmarks), dtype=np.int64)
        # the bound needs the truth of every variable (an observation folder may have poses only)
        points = None
        if extra is not None and (not len(tracks) or tracks[-1] < len(truth.landmarks)):
            points = truth.landmarks[tracks]
            release_mapped_pages()  # the truth's landmarks were read through (mapped in a worker)
        if points is not None and np.all(np.isfinite(points)):
            if progress is not None:
                progress(f"CRLB of {name}", 0, 1)
            crlb = crlb_position_covariances(localizer.smoother, list(localizer.stops), truth.world_T_body,
                                             PointsByTrack(tracks, points), extra)
            consistency_result = consistency(poses[:, :3, 3], truth.positions, covariance, crlb)
    elif traverse.gps_fixes:  # no truth: the fixes are the reference
        along = nees_against_gps(traverse, poses, covariance, vo_inliers)
    return ConfigurationResult(
        name=name,
        kinds=tuple(localizer.kind_names),
        world_T_body=poses,
        position_covariance=covariance,
        steps=steps,
        landmark_ids=final.landmark_ids,
        landmark_positions=final.landmarks,
        tie_links=localizer.tie_links(),
        counters=finished.counters,
        interpolated=list(localizer.interpolated),
        solver="isam2+batch_lm" if job.options.batch else "isam2",
        metrics=metrics,
        consistency=consistency_result,
        metrics_vs_gps=evaluate_against_gps(traverse, poses),
        holdout=holdout_score(traverse, poses, job.held_out),
        nees=along,
    )
