"""The run loop: estimate the motion of every stop once, feed every configuration's localizer
stop by stop, then evaluate each against the reference, the GPS fixes and the held-out fixes."""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .config import EstimatorConfig, Scenario, configuration_problem
from .errors import ConfigError
from .evaluation.consistency import consistency, crlb_position_covariances
from .evaluation.metrics import GPS_REFERENCE_STEP_M, TrajectoryMetrics, compare, decimated_length
from .evaluation.timed import poses_at_times
from .frontend.motion import Motion, VoMotions, dead_reckoning_motion, motion_between, motion_from
from .frontend.stereo_vo import StereoVO
from .frontend.vo_ahead import VoAhead
from .kinds import unavailable
from .localizer import Localizer, StepResult
from .records import GpsFix, GroundTruth, Stop, Traverse
from .results import ConfigurationResult, HoldoutScore, RunOptions, RunResult, SourceInfo
from .sim import simulate

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
    """All a run has done before stop `next_stop`: every configuration's graph and bookkeeping,
    the motions and the per-stop results. Saved at checkpoints; a run given one goes on from it
    and ends with the same estimate as one that was never stopped."""

    next_stop: int
    localizers: dict[str, Localizer]
    motions: list[Motion | None]
    dr_motions: list[Motion | None]
    steps: dict[str, list[StepResult]]
    vo_s: float = 0.0
    elapsed_s: float = 0.0  # wall time spent on the run before this state


class NullListener:
    def start(self, traverse, truth, localizers) -> None:
        pass

    def step(self, stop, motion, steps) -> None:
        pass

    def checkpoint(self, stop) -> None:
        pass

    def finish(self, result) -> None:
        pass


class PeakMemory(NullListener):
    """Notes the process's peak resident memory (MB) at every checkpoint: [(stop, MB)]."""

    def start(self, traverse, truth, localizers) -> None:
        self.samples: list[tuple[int, float]] = []

    def checkpoint(self, stop) -> None:
        self.samples.append((stop.index, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0))


def select_configurations(estimator: EstimatorConfig, traverse: Traverse, requested: tuple[str, ...] | None
                          ) -> tuple[dict[str, list[str]], dict[str, str]]:
    """(name -> kinds to run, name -> why a defined configuration is skipped). Without a request,
    every defined configuration the traverse can feed; a requested one is a defined name or kinds
    joined by '+' (e.g. vo+gps), and one the traverse cannot feed is an error."""
    defined = estimator.configurations
    if requested is None:
        chosen, skipped = {}, {}
        for name, kinds in defined.items():
            reason = unavailable(kinds, traverse)
            if reason:
                skipped[name] = reason
            else:
                chosen[name] = list(kinds)
        if not chosen:
            raise ConfigError(f"{traverse.name}: no configuration can run on this traverse: "
                              + "; ".join(f"{n}: {r}" for n, r in skipped.items()))
        return chosen, skipped
    chosen = {}
    for name in requested:
        kinds = list(defined[name]) if name in defined else name.split("+")
        problem = configuration_problem(kinds)
        if problem:
            raise ConfigError(f"--configs {name}: {problem}; defined configurations: {', '.join(defined)}")
        reason = unavailable(kinds, traverse)
        if reason:
            raise ConfigError(f"--configs {name}: this traverse cannot feed it ({reason})")
        chosen[name] = kinds
    return chosen, {}


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


def run(scenario: Scenario, options: RunOptions = RunOptions(), progress: ProgressCallback | None = None,
        listener: RunListener | None = None) -> RunResult:
    """Simulate the scenario and run every configuration on it."""
    start = time.perf_counter()
    traverse, truth, resolved, info = simulated(scenario, options.seed)
    return run_traverse(traverse, truth, scenario.estimator, resolved.seed, options, progress, listener,
                        source=info, scenario=resolved, started=start)


def simulated(scenario: Scenario, seed: int | None = None, name: str | None = None
              ) -> tuple[Traverse, GroundTruth, Scenario, SourceInfo]:
    """The scenario's traverse and truth for `seed` (default: its own), the scenario resolved
    with that seed (its scenario.toml reproduces the run) and the source's provenance."""
    seed = scenario.seed if seed is None else seed
    traverse, truth = simulate(scenario, seed)
    info = SourceInfo("scenario", name or scenario.name, "simulation ground truth")
    return traverse, truth, scenario.model_copy(update={"seed": seed}), info


def run_traverse(
    traverse: Traverse,
    truth: GroundTruth | None,
    estimator: EstimatorConfig,
    seed: int,
    options: RunOptions = RunOptions(),
    progress: ProgressCallback | None = None,
    listener: RunListener | None = None,
    source: SourceInfo | None = None,
    scenario: Scenario | None = None,
    held_out: tuple[GpsFix, ...] = (),
    started: float | None = None,
    save: Callable[[RunState], None] | None = None,
    resume: RunState | None = None,
    vo_motions: VoMotions | None = None,
) -> RunResult:
    """Estimate the motion of every stop once, feed every configuration's localizer stop by
    stop, then evaluate each against the reference (when there is one) and GPS. At every
    checkpoint `save` gets the run's state; a run given `resume` goes on from that state.
    `vo_motions`: the stops' VO motions when a source has estimated them already (with this
    estimator configuration)."""
    start = time.perf_counter() if started is None else started
    source = source or SourceInfo("traverse", traverse.name, "truth" if truth is not None else "none")
    listener = listener or NullListener()
    n = len(traverse.stops)
    chosen, skipped = select_configurations(estimator, traverse, options.configs)
    if resume is None:
        localizers = {name: Localizer(traverse, kinds, estimator, seed=seed) for name, kinds in chosen.items()}
        state = RunState(0, localizers, [None], [None], {name: [] for name in localizers})
    else:
        state = resume
        localizers = state.localizers
        start -= state.elapsed_s
    any_vo = any(loc.uses_vo for loc in localizers.values())
    vo = StereoVO.for_traverse(traverse, estimator) if any_vo else None
    known = vo_motions.motions if vo_motions is not None and vo_motions.estimator == estimator and len(
        vo_motions.motions) == n else None
    if known is not None and resume is None:
        state.vo_s = vo_motions.seconds
    listener.start(traverse, truth, localizers)

    slip = traverse.wheel_slip
    motions, dr_motions, steps = state.motions, state.dr_motions, state.steps
    ahead = (VoAhead(traverse, estimator, state.next_stop) if vo is not None and known is None
             and options.vo_process and VoAhead.worth_it(traverse, state.next_stop) else None)
    try:
        for k in range(state.next_stop, n):
            stop = traverse.stops[k]
            if k > 0:
                dr_motions.append(dead_reckoning_motion(stop, dr_motions[-1], slip))
                if vo is not None:
                    t0 = time.perf_counter()
                    if known is not None:
                        motions.append(known[k])
                    elif ahead is not None:  # the wait for the worker, not its work, is timed
                        motions.append(motion_from(ahead.result(k), stop, motions[-1], slip))
                    else:
                        motions.append(motion_between(vo, traverse.stops[k - 1], stop, motions[-1], slip))
                    state.vo_s += time.perf_counter() - t0
                else:
                    motions.append(dr_motions[-1])
            now = {name: localizer.step(stop, motions[k] if localizer.uses_vo else dr_motions[k])
                   for name, localizer in localizers.items()}
            for name, step in now.items():
                steps[name].append(step)
            listener.step(stop, motions[k], now)
            if stop.is_site or (k + 1) % CHECKPOINT_EVERY_STOPS == 0:
                state.next_stop, state.elapsed_s = k + 1, time.perf_counter() - start
                if save is not None and k + 1 < n:
                    save(state)
                listener.checkpoint(stop)
            if progress is not None:
                progress("stops", k + 1, n)
    finally:
        if ahead is not None:
            ahead.close()

    results = {}
    for name, localizer in localizers.items():
        if progress is not None:
            progress(f"finishing {name}", 0, 1)
        localizer.finish()
        final = localizer.final(batch=options.batch)
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
                crlb = crlb_position_covariances(localizer.smoother.graph, localizer.stops, truth.world_T_body,
                                                 {j: truth.landmarks[j] for j in localizer.landmarks}, extra)
                consistency_result = consistency(poses[:, :3, 3], truth.positions, covariance, crlb)
        results[name] = ConfigurationResult(
            name=name,
            kinds=tuple(localizer.kind_names),
            world_T_body=poses,
            position_covariance=covariance,
            steps=steps[name],
            landmark_ids=final.landmark_ids,
            landmark_positions=final.landmarks,
            tie_links=localizer.tie_links(),
            counters=localizer.counters(),
            interpolated=list(localizer.interpolated),
            solver="isam2+batch_lm" if options.batch else "isam2",
            metrics=metrics,
            consistency=consistency_result,
            metrics_vs_gps=evaluate_against_gps(traverse, poses),
            holdout=holdout_score(traverse, poses, held_out),
        )
    result = RunResult(source, scenario, estimator, options, seed, traverse, truth, tuple(held_out), motions,
                       results, skipped, time.perf_counter() - start, state.vo_s)
    listener.finish(result)
    return result
