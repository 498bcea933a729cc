"""One group of configurations over a traverse: their localizers fed stop by stop, with
checkpoints, then each evaluated against the reference, the bound (CRLB), the GPS fixes and
the held-out fixes. A run in one process is one group; side by side, each process runs one."""

from __future__ import annotations

import ctypes
import gc
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from .config import EstimatorConfig
from .evaluation.consistency import consistency, crlb_position_covariances
from .evaluation.metrics import GPS_REFERENCE_STEP_M, TrajectoryMetrics, compare, decimated_length
from .evaluation.timed import poses_at_times
from .frontend.motion import Motion, VoMotions, dead_reckoning_motion, motion_between, motion_from
from .frontend.stereo_vo import StereoVO
from .frontend.vo_ahead import VoAhead
from .localizer import Localizer, StepResult
from .records import GpsFix, GroundTruth, Stop, Traverse
from .results import ConfigurationResult, HoldoutScore, ProcessUse, RunOptions, RunResult

CHECKPOINT_EVERY_STOPS = 25  # listeners checkpoint at every site and at least this often

ProgressCallback = Callable[[str, int, int], None]


class RunListener(Protocol):
    """Watches a run stop by stop (the rerun recorder is one). Core code knows only this."""

    def start(self, traverse: Traverse, truth: GroundTruth | None, localizers: dict[str, Localizer]) -> None: ...

    def step(self, stop: Stop, motion: Motion | None, steps: dict[str, StepResult]) -> None: ...

    def checkpoint(self, stop: Stop) -> None:
        """Everything up to `stop` must now survive a crash."""

    def finish(self, result: RunResult) -> None: ...


@dataclass
class RunState:
    """All a group of configurations has done before stop `next_stop` (a run in one process:
    every configuration): their graphs and bookkeeping, the motions and the per-stop results.
    Saved at checkpoints; a run given its groups' states goes on from them and ends with the
    same estimate as one that was never stopped."""

    next_stop: int
    localizers: dict[str, Localizer]
    motions: list[Motion | None]
    dr_motions: list[Motion | None]
    steps: dict[str, list[StepResult]]
    vo_s: float = 0.0
    elapsed_s: float = 0.0  # wall time spent on the run before this state
    memory_mb: list[tuple[int, float]] = field(default_factory=list)  # (stop, peak RSS of the process) at checkpoints
    peak_pss_mb: float = 0.0  # the process's largest proportional set size seen at checkpoints


class NullListener:
    def start(self, traverse, truth, localizers) -> None:
        pass

    def step(self, stop, motion, steps) -> None:
        pass

    def checkpoint(self, stop) -> None:
        pass

    def finish(self, result) -> None:
        pass


def gps_enu(traverse: Traverse, fixes: tuple[GpsFix, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fix times and the fixes converted to ENU (N, 3) with pyproj (default: the traverse's)."""
    fixes = traverse.gps_fixes if fixes is None else fixes
    if not fixes:
        return np.zeros(0), np.zeros((0, 3))
    enu = traverse.origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.h_m for f in fixes])
    return np.array([f.time_s for f in fixes]), enu


def antenna_at_times(traverse: Traverse, world_T_body: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    stops = traverse.stops
    poses = poses_at_times(np.array([s.time_s for s in stops]), np.array([s.departure_s for s in stops]),
                           world_T_body, times_s)
    return np.einsum("nij,j->ni", poses[:, :3, :3], traverse.gps_lever_arm_m) + poses[:, :3, 3]


def evaluate_against_gps(traverse: Traverse, world_T_body: np.ndarray,
                         fixes: tuple[GpsFix, ...] | None = None) -> TrajectoryMetrics | None:
    """The antenna, interpolated to each fix's time, against the fixes (unaligned)."""
    times, enu = gps_enu(traverse, fixes)
    if len(times) < 2:
        return None
    return compare(antenna_at_times(traverse, world_T_body, times), enu, "none",
                   reference_length_m=decimated_length(enu, GPS_REFERENCE_STEP_M))


def holdout_score(traverse: Traverse, world_T_body: np.ndarray, held_out: tuple[GpsFix, ...]) -> HoldoutScore | None:
    if not held_out:
        return None
    times, enu = gps_enu(traverse, held_out)
    antenna = antenna_at_times(traverse, world_T_body, times)
    rms = float(np.sqrt(np.mean(np.sum((antenna[:, :2] - enu[:, :2]) ** 2, axis=1))))
    drms = float(np.sqrt(np.mean([2.0 * f.sigma_horizontal_m**2 for f in held_out])))
    return HoldoutScore(len(held_out), rms, drms)


class Checkpoints(Protocol):
    """Saves a group's state at a checkpoint (io/checkpoint.CheckpointWriter)."""

    def __call__(self, state: RunState) -> None: ...

    def part(self, index: int) -> Checkpoints:
        """The writer of group `index` when groups run side by side."""

    def log_folder(self, configuration: str) -> Path:
        """Where a configuration's smoother keeps its update log (the saved states refer to it)."""


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
    motions: list[Motion | None]
    vo_s: float
    process: ProcessUse


def run_group(job: GroupJob, state: RunState | None, known: VoMotions | None, save: Checkpoints | None,
              progress: ProgressCallback | None, listener: RunListener | None, start: float,
              label: str = "run") -> GroupOutcome:
    """A group's configurations stop by stop in this process, then evaluated. Motions the
    state does not have are estimated as the stops come (`known`: a source's; else the VO,
    ahead in a second process on long traverses when the options allow one)."""
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
    try:
        _step_through(traverse, state, vo_motion if any_vo else None, save, progress, listener, start)
    finally:
        gc.unfreeze()
        if ahead is not None:
            ahead.close()
    results = {}
    for name in list(state.localizers):
        if progress is not None:
            progress(f"finishing {name}", 0, 1)
        results[name] = _configuration_result(job, name, state.localizers[name], state.steps[name], progress)
        del state.localizers[name]  # its graphs are no more use: their memory goes to the next one's bounds
        release_memory()
    _sample_memory(state, n - 1)
    use = ProcessUse(label, os.getpid(), tuple(results), time.perf_counter() - began,
                     time.process_time() - began_cpu, state.memory_mb, state.peak_pss_mb or None)
    return GroupOutcome(results, state.motions, state.vo_s, use)


def new_state(job: GroupJob) -> RunState:
    localizers = {name: Localizer(job.traverse, kinds, job.estimator, seed=job.seed)
                  for name, kinds in job.configs.items()}
    return RunState(0, localizers, [None], [None], {name: [] for name in localizers})


def peak_rss_mb() -> float:
    """This process's peak resident memory so far."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def settle_garbage_collector() -> None:
    """Collect, then set aside every object that survived from Python's garbage collector
    (`gc.freeze`), which otherwise walks all of them at each of its full collections: the
    traverse's stops and everything the run built so far. Without this the collections came
    at random stops and grew with the traverse (vo_sites beside full on long_traverse: median
    update 0.19 ms in the first km, 0.53 in the eleventh, 0.39 with the collector off).
    Called at checkpoints, so each collection walks what a few stops made; `gc.unfreeze` at
    the end of the run hands the rest back."""
    gc.collect()
    gc.freeze()


def release_memory() -> None:
    """Hand the memory of what was freed back to the system: glibc keeps it otherwise, and the
    process's footprint stays where its largest graph left it."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def pss_mb() -> float | None:
    """This process's proportional set size now (Linux): its resident memory with each page
    shared with other processes (the fork server's imports) counted as its share; None where
    the kernel does not say."""
    try:
        with open("/proc/self/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def _sample_memory(state: RunState, stop: int) -> None:
    state.memory_mb.append((stop, peak_rss_mb()))
    state.peak_pss_mb = max(state.peak_pss_mb, pss_mb() or 0.0)


def _step_through(traverse: Traverse, state: RunState, vo_motion: Callable[[int, Motion | None], Motion] | None,
                  save: Checkpoints | None, progress: ProgressCallback | None, listener: RunListener,
                  start: float) -> None:
    """Feed the state's localizers every stop from `state.next_stop` on; a stop's motion is
    estimated here unless the state has it already."""
    n = len(traverse.stops)
    slip = traverse.wheel_slip
    motions, dr_motions, steps = state.motions, state.dr_motions, state.steps
    for k in range(state.next_stop, n):
        stop = traverse.stops[k]
        if k > 0 and len(dr_motions) <= k:
            dr_motions.append(dead_reckoning_motion(stop, dr_motions[-1], slip))
        if k > 0 and len(motions) <= k:
            t0 = time.perf_counter()
            motions.append(vo_motion(k, motions[-1]) if vo_motion is not None else dr_motions[k])
            state.vo_s += time.perf_counter() - t0
        now = {name: localizer.step(stop, motions[k] if localizer.uses_vo else dr_motions[k])
               for name, localizer in state.localizers.items()}
        for name, step in now.items():
            steps[name].append(step)
        listener.step(stop, motions[k], now)
        if stop.is_site or (k + 1) % CHECKPOINT_EVERY_STOPS == 0:
            state.next_stop, state.elapsed_s = k + 1, time.perf_counter() - start
            settle_garbage_collector()
            _sample_memory(state, k)
            if save is not None and k + 1 < n:
                save(state)
            listener.checkpoint(stop)
        if progress is not None:
            progress("stops", k + 1, n)
    state.next_stop = n


def _configuration_result(job: GroupJob, name: str, localizer: Localizer, steps: list[StepResult],
                          progress: ProgressCallback | None) -> ConfigurationResult:
    """A configuration's final estimate, its covariances, and its metrics against the
    reference, the bound (CRLB) and GPS."""
    traverse, truth = job.traverse, job.truth
    localizer.finish()
    final = localizer.final(batch=job.options.batch)
    poses = final.world_T_body
    alignment = "none" if "gps" in localizer.kinds else "se3"
    metrics = consistency_result = None
    covariance = localizer.position_covariances()
    if truth is not None:
        metrics = compare(poses[:, :3, 3], truth.positions, alignment, poses, truth.world_T_body)
        extra = localizer.true_values(truth)
        # the bound needs the truth of every variable (an observation folder may have poses only)
        if extra is not None and all(j < len(truth.landmarks) and np.all(np.isfinite(truth.landmarks[j]))
                                     for j in localizer.landmarks):
            if progress is not None:
                progress(f"CRLB of {name}", 0, 1)
            crlb = crlb_position_covariances(localizer.smoother, localizer.stops, truth.world_T_body,
                                             {j: truth.landmarks[j] for j in localizer.landmarks}, extra)
            consistency_result = consistency(poses[:, :3, 3], truth.positions, covariance, crlb)
    return ConfigurationResult(
        name=name,
        kinds=tuple(localizer.kind_names),
        world_T_body=poses,
        position_covariance=covariance,
        steps=steps,
        landmark_ids=final.landmark_ids,
        landmark_positions=final.landmarks,
        tie_links=localizer.tie_links(),
        counters=localizer.counters(),
        interpolated=list(localizer.interpolated),
        solver="isam2+batch_lm" if job.options.batch else "isam2",
        metrics=metrics,
        consistency=consistency_result,
        metrics_vs_gps=evaluate_against_gps(traverse, poses),
        holdout=holdout_score(traverse, poses, job.held_out),
    )
