"""The run loop: simulate the traverse, estimate the motion of every stop once, feed every
configuration's localizer stop by stop, then evaluate each against truth and GPS."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .config import EstimatorConfig, Scenario
from .evaluation.consistency import Consistency, consistency, crlb_position_covariances
from .evaluation.metrics import GPS_REFERENCE_STEP_M, TrajectoryMetrics, compare, decimated_length
from .frontend.motion import Motion, dead_reckoning_motion, motion_between
from .frontend.stereo_vo import StereoVO
from .localizer import Localizer, LocalizerOptions, StepResult
from .records import GroundTruth, Stop, Traverse
from .sim import simulate

CONFIGURATIONS: dict[str, LocalizerOptions] = {
    # Wheel odometry + IMU alone (the baseline VO is meant to beat); runs when the traverse has it.
    "dead_reckoning": LocalizerOptions(use_sites=False, use_hrc=False, use_gps=False, use_vo=False),
    "vo": LocalizerOptions(use_sites=False, use_hrc=False, use_gps=False),
    "vo_sites": LocalizerOptions(use_sites=True, use_hrc=False, use_gps=False),
    "vo_sites_hrc": LocalizerOptions(use_sites=True, use_hrc=True, use_gps=False),
    "full": LocalizerOptions(use_sites=True, use_hrc=True, use_gps=True),
}
CHECKPOINT_EVERY_STOPS = 25  # listeners checkpoint at every site and at least this often


@dataclass(frozen=True)
class RunOptions:
    seed: int | None = None
    use_gps: bool = True
    use_sites: bool = True
    use_hrc: bool = True
    batch: bool = False

    def configurations(self) -> list[str]:
        names = []
        for name, opt in CONFIGURATIONS.items():
            if (opt.use_gps and not self.use_gps) or (opt.use_sites and not self.use_sites):
                continue
            if opt.use_hrc and not self.use_hrc:
                continue
            names.append(name)
        return names


@dataclass(frozen=True)
class ConfigurationResult:
    name: str
    world_T_body: np.ndarray  # (N, 4, 4)
    position_covariance: np.ndarray  # (N, 3, 3) world-frame marginal of each position, m^2 (iSAM2)
    steps: list[StepResult]  # one per stop
    landmark_ids: np.ndarray  # (M,)
    landmark_positions: np.ndarray  # (M, 3) final landmark estimates, world
    tie_links: list[tuple[int, int]]  # (track, site stop)
    bridged_stops: int
    rejected_tie_points: int  # candidate ties whose two sites' triangulations disagree
    rejected_tie_views: int  # later sites' views of a landmark that disagree with it
    rejected_hrc_measurements: int
    solver: str
    metrics: TrajectoryMetrics | None  # against the reference; None without one
    consistency: Consistency | None  # CRLB and NEES against simulation truth; None without landmark truth
    metrics_vs_gps: TrajectoryMetrics | None

    @property
    def update_ms(self) -> np.ndarray:
        """Wall time of each stop's iSAM2 update."""
        return np.array([s.update_ms for s in self.steps])

    @property
    def landmarks(self) -> int:
        return len(self.landmark_ids)

    @property
    def gps_fixes_used(self) -> int:
        return sum(s.gps_used for s in self.steps)

    @property
    def gps_outliers(self) -> int:
        """Fixes failing the 99 % chi-square test at the estimate after their update."""
        return sum(s.gps_outlier for s in self.steps)


@dataclass(frozen=True)
class RunResult:
    scenario: Scenario | None  # None for a traverse read from an observation folder
    seed: int
    traverse: Traverse
    truth: GroundTruth | None  # None when a recorded traverse comes without a reference
    motions: list[Motion | None]
    configurations: dict[str, ConfigurationResult]
    wall_s: float
    vo_s: float

    @property
    def update_ms(self) -> np.ndarray:
        return np.concatenate([c.update_ms for c in self.configurations.values()])

    @property
    def name(self) -> str:
        return self.traverse.name

    @property
    def description(self) -> str:
        return self.scenario.description if self.scenario is not None else "traverse from an observation folder"


ProgressCallback = Callable[[str, int, int], None]


class RunListener(Protocol):
    """Watches a run stop by stop (the rerun recorder is one). Core code knows only this."""

    def start(self, traverse: Traverse, truth: GroundTruth | None, localizers: dict[str, Localizer]) -> None: ...

    def step(self, stop: Stop, motion: Motion | None, steps: dict[str, StepResult]) -> None: ...

    def checkpoint(self, stop: Stop) -> None:
        """Everything up to `stop` must now survive a crash."""

    def finish(self, result: RunResult) -> None: ...


class NullListener:
    def start(self, traverse, truth, localizers) -> None:
        pass

    def step(self, stop, motion, steps) -> None:
        pass

    def checkpoint(self, stop) -> None:
        pass

    def finish(self, result) -> None:
        pass


def gps_enu(traverse: Traverse) -> tuple[np.ndarray, np.ndarray]:
    """Stop indices with a fix and the fixes converted to ENU (N, 3) with pyproj."""
    idx = np.array([s.index for s in traverse.stops if s.gps is not None], dtype=int)
    if len(idx) == 0:
        return idx, np.zeros((0, 3))
    fixes = [traverse.stops[i].gps for i in idx]
    enu = traverse.origin.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], [f.h_m for f in fixes])
    return idx, enu


def evaluate_against_gps(traverse: Traverse, world_T_body: np.ndarray) -> TrajectoryMetrics | None:
    idx, enu = gps_enu(traverse)
    if len(idx) < 2:
        return None
    antenna = np.einsum("nij,j->ni", world_T_body[idx, :3, :3], traverse.gps_lever_arm_m)
    antenna += world_T_body[idx, :3, 3]
    return compare(antenna, enu, "none", reference_length_m=decimated_length(enu, GPS_REFERENCE_STEP_M))


def run(
    scenario: Scenario,
    options: RunOptions = RunOptions(),
    progress: ProgressCallback | None = None,
    listener: RunListener | None = None,
) -> RunResult:
    """Simulate the scenario and run every configuration on it."""
    start = time.perf_counter()
    seed = scenario.seed if options.seed is None else options.seed
    traverse, truth = simulate(scenario, seed)
    return run_traverse(traverse, truth, scenario.estimator, seed, options, progress, listener, scenario, start)


def run_traverse(
    traverse: Traverse,
    truth: GroundTruth | None,
    estimator: EstimatorConfig,
    seed: int,
    options: RunOptions = RunOptions(),
    progress: ProgressCallback | None = None,
    listener: RunListener | None = None,
    scenario: Scenario | None = None,
    started: float | None = None,
) -> RunResult:
    """Estimate the motion of every stop once, feed every configuration's localizer stop by
    stop, then evaluate each against the reference (when there is one) and GPS."""
    start = time.perf_counter() if started is None else started
    listener = listener or NullListener()
    n = len(traverse.stops)
    vo = StereoVO.for_traverse(traverse, estimator)
    names = options.configurations()
    if not any(s.dead_reckoning is not None for s in traverse.stops):
        names = [name for name in names if CONFIGURATIONS[name].use_vo]
    localizers = {name: Localizer(traverse, CONFIGURATIONS[name], estimator, seed=seed) for name in names}
    listener.start(traverse, truth, localizers)

    motions: list[Motion | None] = [None]
    dr_motions: list[Motion | None] = [None]
    steps: dict[str, list[StepResult]] = {name: [] for name in names}
    vo_s = 0.0
    for k, stop in enumerate(traverse.stops):
        if k > 0:
            t0 = time.perf_counter()
            motions.append(motion_between(vo, traverse.stops[k - 1], stop, motions[-1]))
            vo_s += time.perf_counter() - t0
            dr_motions.append(dead_reckoning_motion(stop, dr_motions[-1]))
        now = {name: localizer.step(stop, motions[k] if CONFIGURATIONS[name].use_vo else dr_motions[k])
               for name, localizer in localizers.items()}
        for name, step in now.items():
            steps[name].append(step)
        listener.step(stop, motions[k], now)
        if stop.is_site or (k + 1) % CHECKPOINT_EVERY_STOPS == 0:
            listener.checkpoint(stop)
        if progress is not None:
            progress("stops", k + 1, n)

    results = {}
    for name, localizer in localizers.items():
        if progress is not None:
            progress(f"finishing {name}", 0, 1)
        final = localizer.final(batch=options.batch)
        poses = final.world_T_body
        alignment = "none" if CONFIGURATIONS[name].use_gps else "se3"
        metrics = consistency_result = None
        covariance = np.stack([localizer.position_covariance(k) for k in localizer.stops])
        if truth is not None:
            metrics = compare(poses[:, :3, 3], truth.positions, alignment, poses, truth.world_T_body)
            # an observation folder's truth has poses only; the bound needs every landmark's truth
            if all(j < len(truth.landmarks) for j in localizer.landmarks):
                if progress is not None:
                    progress(f"CRLB of {name}", 0, 1)
                crlb = crlb_position_covariances(localizer.smoother.graph, localizer.stops, truth.world_T_body,
                                                 {j: truth.landmarks[j] for j in localizer.landmarks})
                consistency_result = consistency(poses[:, :3, 3], truth.positions, covariance, crlb)
        results[name] = ConfigurationResult(
            name=name,
            world_T_body=poses,
            position_covariance=covariance,
            steps=steps[name],
            landmark_ids=final.landmark_ids,
            landmark_positions=final.landmarks,
            tie_links=localizer.tie_links(),
            bridged_stops=localizer.bridged_stops,
            rejected_tie_points=localizer.rejected_ties,
            rejected_tie_views=localizer.rejected_tie_views,
            rejected_hrc_measurements=localizer.rejected_hrc,
            solver="isam2+batch_lm" if options.batch else "isam2",
            metrics=metrics,
            consistency=consistency_result,
            metrics_vs_gps=evaluate_against_gps(traverse, poses),
        )
    result = RunResult(scenario, seed, traverse, truth, motions, results, time.perf_counter() - start, vo_s)
    listener.finish(result)
    return result


def percentiles(ms: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


def metrics_document(result: RunResult) -> dict:
    """The content of metrics.json."""
    vo_motions = [m for m in result.motions[1:] if m is not None]
    configs = {}
    for name, c in result.configurations.items():
        entry = c.metrics.as_dict() if c.metrics is not None else {}
        if c.consistency is not None:
            entry.update(c.consistency.as_dict())
        entry.update(
            bridged_stops=c.bridged_stops,
            landmarks=c.landmarks,
            rejected_tie_points=c.rejected_tie_points,
            rejected_tie_views=c.rejected_tie_views,
            rejected_hrc_measurements=c.rejected_hrc_measurements,
            gps_fixes_used=c.gps_fixes_used,
            gps_outliers=c.gps_outliers,
            solver=c.solver,
            isam2_update_ms=percentiles(c.update_ms),
            vs_gps=c.metrics_vs_gps.as_dict() if c.metrics_vs_gps is not None else None,
        )
        configs[name] = entry
    return {
        "scenario": result.name,
        "seed": result.seed,
        "rig": result.traverse.rig.name,
        "stops": len(result.traverse.stops),
        "sites": sum(s.is_site for s in result.traverse.stops),
        "gps_fixes": sum(s.gps is not None for s in result.traverse.stops),
        "reference": ("simulation ground truth" if result.scenario is not None else
                      "truth.kitti of the observation folder" if result.truth is not None else "none")
                     + " (configs.*), GPS fixes (configs.*.vs_gps)",
        "vo": {
            "stops_bridged": sum(m.bridged for m in vo_motions),
            "bridge_sources": sorted({m.source for m in vo_motions if m.bridged}),
            "median_inliers": float(np.median([m.vo_inliers for m in vo_motions])) if vo_motions else 0.0,
        },
        "configs": configs,
        "timing": {
            "isam2_update_ms": percentiles(result.update_ms),
            "vo_s": result.vo_s,
            "wall_s": result.wall_s,
        },
    }
