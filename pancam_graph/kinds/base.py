"""What a measurement kind is: everything about one kind of measurement, in one module.

A kind owns its factor builder, its gate, its counters and the metrics it reports. The localizer
calls, for every stop: `pose_times` (measurements between the previous stop and this one that
need a pose of their own), `update_before` (why the estimate must be updated first, or None),
`add` (this stop's factors, before the update), `after_update` (checks against the updated
estimate; why it must be updated again, or None); and `counters` once at the end.

A kind whose measurements are not part of every traverse's stops (a sun sensor, say) also
declares, all optional:
- `Settings`: its estimator constants, the section `[estimator.<name>]` of a scenario or an
  observation folder's manifest;
- `Sensor`: how a scenario simulates it, the scenario's section `[<name>]`, and `simulate`;
- `columns`, `to_rows` and `from_rows`: its table `<name>.csv` in an observation folder.
Its records travel in `Traverse.measurements[name]`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Protocol

import gtsam
import numpy as np
from pydantic import BaseModel, ConfigDict

from ..records import GroundTruth, Stop, Traverse

NO_TIE_LINKS = np.zeros((0, 2), dtype=np.int64)  # (track, site stop) rows: a kind that ties nothing
# (key_a, key_b, a_T_b, covariance) -> factor: a motion step's between factor; a VO step's also
# takes the step's calibration sensitivity (Motion.calibration_sensitivity, None where unknown)
MotionFactor = Callable[..., gtsam.NonlinearFactor]
# (stop key, landmark key, uvv, camera, body_T_left, noise) -> factor: a site's stereo view
SiteStereoFactor = Callable[[int, int, np.ndarray, tuple, np.ndarray, tuple], gtsam.NonlinearFactor]

_REGISTRY: dict[str, type[Kind]] = {}


class Section(BaseModel):
    """The base of a kind's configuration sections: a frozen pydantic model that refuses unknown
    keys and non-finite numbers."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def registered() -> dict[str, type[Kind]]:
    """Every kind by name, in build order."""
    return dict(sorted(_REGISTRY.items(), key=lambda item: item[1].order))


class StepCounts(dict):
    """What the kinds did at one stop, by counter name (each kind's `step_counters`), filled in
    during the step; a counter no kind set keeps its declared default."""

    def add(self, name: str, value: float = 1) -> None:
        self[name] = self.get(name, 0) + value


class Host(Protocol):
    """What a kind sees of the localizer that builds it (localizer.Localizer)."""

    traverse: Traverse
    estimator: Any  # config.EstimatorConfig, with the kind's own section as `estimator.<name>`
    smoother: Any  # graph.smoother.Smoother
    previous_stop: Stop | None
    bridged_stops: int
    rng: np.random.Generator
    site_stereo_factor: SiteStereoFactor | None  # a kind's (builds_site_stereo), or None: factors.stereo
    # a site's stereo pixels (N, 3) as the pair would have seen them calibrated as its estimate
    # says (the kind that builds_site_stereo), or None: the pixels as they are
    site_stereo_pixels: Callable[[np.ndarray], np.ndarray] | None

    def kind(self, name: str) -> Kind: ...

    def pose_key_at(self, time_s: float) -> int: ...


class Kind:
    name: ClassVar[str]
    order: ClassVar[int]  # build and call order: a kind that hooks into another comes after it
    Settings: ClassVar[type[Section] | None] = None  # [estimator.<name>]
    Sensor: ClassVar[type[Section] | None] = None  # a scenario's [<name>]: how it is simulated
    columns: ClassVar[tuple[str, ...]] = ()  # its observation-folder table, <name>.csv
    # Its counters at each stop (steps.csv columns), with the value of a stop where it did nothing
    # (and of a configuration without it): counts 0, a largest-of None.
    step_counters: ClassVar[dict[str, float | None]] = {}
    # Its counters over the whole traverse (metrics.json), the same for a configuration without it.
    counter_defaults: ClassVar[dict[str, float | list]] = {}
    # Its list counters that the user must hear about when not empty (printed as warnings), with
    # what their entries are: {"orbital_uncovered_stops": "site stops no orbital map covers"}.
    warning_counters: ClassVar[dict[str, str]] = {}
    # What the run loop needs to know of a kind, so that it names none:
    motion: ClassVar[str | None] = None  # the motion between stops it stands for: "vo" or "dead_reckoning"
    needs: ClassVar[dict[str, str]] = {}  # kinds it hooks into, which a configuration must have too: why
    absolute: ClassVar[bool] = False  # an absolute position (bounds the uncertainty: GPS)
    cost: ClassVar[float] = 0.0  # time per stop it adds, relative to plain VO's (balances groups of configurations)
    # The stops' image records it reads (Stop.panorama, .hrc, .ground): a worker process running
    # configurations without it is sent a traverse without them.
    stop_records: ClassVar[frozenset[str]] = frozenset()
    # The motion whose between factors it builds instead of the plain ones (motion_factor):
    # "odometry" (every dead-reckoning step, bridges of VO included) or "vo" (every VO step).
    builds_motion: ClassVar[str | None] = None
    # Whether it builds the sites' stereo views' factors instead of the plain ones (site_stereo_factor).
    builds_site_stereo: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:  # a family of kinds (motion.MotionKind), not a kind
            return
        if cls.name in _REGISTRY:
            raise TypeError(f"two measurement kinds are named {cls.name!r}")
        _REGISTRY[cls.name] = cls

    def __init__(self, localizer: Host):
        self.loc = localizer

    # What it reads, in words: a traverse without any is "a traverse with no <records>".
    records: ClassVar[str] = ""

    @classmethod
    def has_records(cls, traverse: Traverse) -> bool:
        """Whether the traverse holds any of this kind's measurements (its own records, by
        default: Traverse.measurements[name])."""
        return bool(traverse.measurements.get(cls.name))

    @classmethod
    def unavailable(cls, traverse: Traverse) -> str | None:
        """Why this traverse cannot feed the kind, or None."""
        if cls.records and not cls.has_records(traverse):
            return f"the traverse has no {cls.records}"
        return None

    @classmethod
    def scenario_unavailable(cls, scenario) -> str | None:
        """Why a simulation of this scenario (config.Scenario) cannot feed the kind, or None: by
        default, a kind simulated from a scenario section (`Sensor`) needs that section enabled."""
        if cls.Sensor is None:
            return None
        section = getattr(scenario, cls.name, None)
        if section is None or not getattr(section, "enabled", True):
            return f"the scenario simulates no {cls.records or cls.name} (its [{cls.name}] is not enabled)"
        return None

    @classmethod
    def check_traverse(cls, traverse: Traverse) -> None:
        """Raise InputError (naming the file) when the traverse's records break this kind's rules;
        called when a configuration with it is chosen, before the run writes anything."""

    @classmethod
    def check_scenario(cls, scenario) -> None:
        """Raise ValueError (the message for the user) when a scenario breaks this kind's rules
        (config.Scenario: its origin, its sections, its estimator's sections)."""

    # -- records: simulated, written and read (kinds with Traverse.measurements) ---------------

    @classmethod
    def simulate(cls, sensor: Section, traverse: Traverse, truth: GroundTruth,
                 rng: np.random.Generator) -> tuple:
        """This kind's records of a simulated traverse, drawn from the truth (`Sensor` kinds)."""
        return ()

    @classmethod
    def simulate_with_truth(cls, sensor: Section, traverse: Traverse, truth: GroundTruth,
                            rng: np.random.Generator) -> tuple[tuple, dict[str, float]]:
        """Its records and the true values of its own variables that the simulation drew (for
        GroundTruth.kinds[name]); a kind whose sensor draws such a state overrides this."""
        return cls.simulate(sensor, traverse, truth, rng), {}

    @classmethod
    def to_rows(cls, records: tuple) -> list[tuple[float, ...]]:
        """The records as rows of `columns`."""
        return []

    @classmethod
    def from_rows(cls, rows: list[tuple[int, tuple[float, ...]]], traverse: Traverse) -> tuple:
        """Records from (line, numbers in `columns` order) rows; a row that does not fit the
        traverse raises RowError naming its line."""
        return ()

    # -- the step ------------------------------------------------------------------------------

    def pose_times(self, prev: Stop, stop: Stop) -> list[float]:
        """Times strictly inside the drive from `prev` to `stop` at which this kind needs a pose."""
        return []

    def motion_factor(self) -> MotionFactor | None:
        """The factor builder for `builds_motion`'s steps: (key_a, key_b, a_T_b, covariance) ->
        factor, with this kind's shared variables in it; for "vo", (key_a, key_b, a_T_b,
        covariance, calibration sensitivity or None) -> factor."""
        return None

    def site_stereo_factor(self) -> SiteStereoFactor | None:
        """The factor builder of a site's stereo view when `builds_site_stereo`: (stop key,
        landmark key, (u_left, u_right, v), camera (fx, fy, cx, cy, baseline), body_T_left 4x4,
        noise (kernel, k, sigma_px, tie_sigma_px)) -> factor, plain arguments a checkpoint can pickle."""
        return None

    def site_stereo_pixels(self, uvv: np.ndarray) -> np.ndarray:
        """With `builds_site_stereo`: a site's stereo pixels (N, 3) corrected by this kind's
        current estimate of the pair's error, for what triangulates them outside the graph."""
        return uvv

    def update_before(self, stop: Stop) -> str | None:
        """Why the estimate must be updated before this kind's factors of `stop` (a gate or a
        registration that reads the stop's marginals), or None. The localizer makes that update."""
        return None

    def add(self, stop: Stop, counts: StepCounts) -> None:
        """This stop's factors (before the stop's update)."""

    def after_update(self, stop: Stop, counts: StepCounts) -> str | None:
        """Checks against the updated estimate; why it must be updated again (factors this kind
        replaced, weighed at it), or None. The localizer makes that update before the next kind's."""
        return None

    def true_values(self, truth: GroundTruth, values: gtsam.Values) -> bool:
        """Insert the true values of this kind's own variables (for the CRLB); False when unknown."""
        return True

    def against_truth(self, truth: GroundTruth) -> dict[str, float]:
        """Its own variables' estimates against the truth (metrics.json), where the truth has them."""
        return {}

    def finish(self) -> None:
        """The traverse is over: anything left to account for."""

    def counters(self) -> dict[str, int | float | list[str]]:
        """What this kind did over the whole traverse, for metrics.json; a motion kind: the stops
        whose motion was bridged (dead reckoning's: every step after the first)."""
        return {"bridged_stops": self.loc.bridged_stops} if self.motion else {}

    def landmarks(self) -> set[int]:
        """The landmark variables it made (track ids)."""
        return set()

    def tie_links(self) -> np.ndarray:
        """(K, 2) (track, site stop) of each tie it made, for plots and rerun."""
        return NO_TIE_LINKS


class RowError(ValueError):
    """A row of a kind's table that does not fit the traverse (the reader adds file and line)."""

    def __init__(self, line: int, message: str):
        super().__init__(message)
        self.line = line
