"""The typed result of a run, owned below the run loop: what `pipeline` produces, what the
results folder holds (store/results_folder.py writes it and reads it back, store/documents.py
lays out its metrics.json and run.toml), what plots, the report and rerun show."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import EstimatorConfig, Scenario
from ..evaluation.consistency import Consistency, NeesAlongRun
from ..evaluation.gps_check import HoldoutScore
from ..evaluation.metrics import TrajectoryMetrics
from ..frontend.motion import Motions
from ..kinds import COUNTER_DEFAULTS
from ..records import GpsFix, GroundTruth, Traverse
from .localizer import InterpolatedPose
from .step_table import StepTable


@dataclass(frozen=True)
class RunOptions:
    """How to run a traverse: which configurations (None: every one the traverse can feed),
    the seed of a simulated scenario, batch polishing."""

    seed: int | None = None
    configs: tuple[str, ...] | None = None
    batch: bool = False
    # Processes the run may use. More than one: the configurations run in groups side by side
    # (side_by_side.py) on traverses of `side_by_side_min_stops` or more, or with a listener or
    # on a shorter one, the stereo VO goes ahead in a second process (frontend/vo_ahead.py). The
    # CLI uses every core; a script that does must guard its main module (multiprocessing "spawn").
    processes: int = 1
    side_by_side_min_stops: int = 300  # below this, starting the processes costs more than they save
    vo_error_model: str | None = None  # given for this run, instead of the source's own


@dataclass(frozen=True)
class SourceInfo:
    """Where a traverse came from: the kind of source, the path or name given, what the reader
    assumed, and the source's options (e.g. which fixes were held out)."""

    kind: str  # scenario, observations, rosbag, kitti_raw
    path: str
    reference: str  # what the metrics compare against, in words
    notes: tuple[str, ...] = ()
    options: dict = field(default_factory=dict)
    # What the world frame's first two axes are (plots' axis names): ENU, or a recorded frame
    axes: tuple[str, str] = ("east", "north")
    georeferenced: bool = True  # the local frame's origin is a place on the body (else no geographic file)
    # Each stop's rover motion counter (site, drive) when the source has one (rover products);
    # else the localization product numbers sites by the panorama stops and drives from each.
    stop_counters: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True)
class ConfigurationResult:
    name: str
    kinds: tuple[str, ...]
    world_T_body: np.ndarray  # (N, 4, 4)
    position_covariance: np.ndarray  # (N, 3, 3) world-frame marginal of each position, m^2 (iSAM2)
    steps: StepTable  # one per stop
    landmark_ids: np.ndarray  # (M,)
    landmark_positions: np.ndarray  # (M, 3) final landmark estimates, world
    tie_links: np.ndarray  # (K, 2) int: (track, site stop)
    counters: dict  # what each kind did (kinds/*.counters)
    interpolated: list[InterpolatedPose]
    solver: str
    metrics: TrajectoryMetrics | None  # against the reference; None without one
    consistency: Consistency | None  # CRLB and NEES against truth; None without full truth
    metrics_vs_gps: TrajectoryMetrics | None  # against the fixes in the graph
    holdout: HoldoutScore | None = None  # against the held-out fixes
    nees: NeesAlongRun | None = None  # NEES against the truth (each stop) or GPS (each fix); None without either

    @property
    def update_ms(self) -> np.ndarray:
        """Wall time of each stop's iSAM2 update."""
        return self.steps.update_ms

    @property
    def landmarks(self) -> int:
        return len(self.landmark_ids)

    @property
    def bridged_stops(self) -> int:
        return int(self.counters.get("bridged_stops", 0))

    def counter(self, name: str) -> float | list:
        """A whole-traverse counter of a kind (its default for a configuration without it)."""
        return self.counters.get(name, COUNTER_DEFAULTS.get(name, 0))


@dataclass(frozen=True)
class ProcessUse:
    """A group of configurations and the process that ran it: which configurations, for how
    long (s, from its first stop to its configurations evaluated) and the process's resident
    memory, (stop, MB) at the run's checkpoints (a process may run several groups),
    and its largest proportional set size (shared pages counted as its share; None: unknown)."""

    label: str
    pid: int
    configurations: tuple[str, ...]
    seconds: float
    cpu_seconds: float  # of the process in that time (less than `seconds`: it shared a core or waited)
    memory_mb: list[tuple[int, float]]
    peak_pss_mb: float | None = None


@dataclass(frozen=True)
class RunResult:
    source: SourceInfo
    scenario: Scenario | None  # the simulated scenario, resolved; None for recorded sources
    estimator: EstimatorConfig
    options: RunOptions
    seed: int
    traverse: Traverse
    truth: GroundTruth | None  # None when a recorded traverse comes without a reference
    held_out_fixes: tuple[GpsFix, ...]
    motions: Motions
    configurations: dict[str, ConfigurationResult]
    skipped: dict[str, str]  # defined configurations the traverse cannot feed, with the reason
    wall_s: float
    vo_s: float
    processes: list[ProcessUse] = field(default_factory=list)  # that ran the configurations
    # the most resident memory the run's processes held at once (MB; in one process: its peak)
    peak_memory_mb: float | None = None

    @property
    def update_ms(self) -> np.ndarray:
        return np.concatenate([c.update_ms for c in self.configurations.values()])

    @property
    def name(self) -> str:
        return self.traverse.name

    @property
    def title(self) -> str:
        """The run's name, with its seed where it is a simulation (a recording has none)."""
        return f"{self.name}, seed {self.seed}" if self.scenario is not None else self.name

    @property
    def description(self) -> str:
        if self.scenario is not None:
            return self.scenario.description
        return f"{self.source.kind} {self.source.path}"

    def reference_positions(self) -> tuple[np.ndarray, str]:
        """The truth at each stop, or without one the last (richest) configuration's estimate,
        and which it is."""
        if self.truth is not None:
            return self.truth.positions, "truth"
        name = list(self.configurations)[-1]
        return self.configurations[name].world_T_body[:, :3, 3], f"{name} estimate (no truth)"

    def reference_distance(self) -> np.ndarray:
        """Distance travelled along the reference at each stop (m)."""
        return travelled(self.reference_positions()[0])


def travelled(positions: np.ndarray) -> np.ndarray:
    """Distance travelled along a polyline at each of its points (m)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def percentiles(ms: np.ndarray) -> dict[str, float]:
    if len(ms) == 0:
        return {"median": 0.0, "p99": 0.0, "max": 0.0}
    return {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


def cost_along(result: RunResult, window_m: float = 1000.0) -> dict[str, list[dict]]:
    """Per configuration, the iSAM2 update time in windows of `window_m` along the reference
    path: is the cost flat along the traverse?"""
    distance = result.reference_distance()
    out = {}
    for name, c in result.configurations.items():
        stops = c.steps.stops
        window = (distance[stops] // window_m).astype(int)
        ms = c.update_ms
        out[name] = [{"from_m": w * window_m, "updates": int((window == w).sum()), **percentiles(ms[window == w])}
                     for w in range(int(window.max()) + 1) if (window == w).any()]
    return out


def memory_along(result: RunResult) -> dict[str, list[tuple[int, float]]]:
    """Each group of configurations' process: (stop, its resident memory in MB) at each
    checkpoint. Flat after the first window is a run that keeps nothing per stop in memory."""
    return {f"{p.label}: {', '.join(p.configurations)}": list(p.memory_mb) for p in result.processes
            if p.memory_mb}
