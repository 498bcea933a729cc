"""The rover's own onboard estimate as a measurement: consecutive onboard poses (wheel odometry
with IMU attitude, onboard VO where it ran: what a mission product's label carries) become the
motion between stops, with an error model stated per step, and the onboard tilt at each stop
(the accelerometers' gravity while the rover stands) becomes an attitude factor. A motion kind
like dead_reckoning, so it goes with sites, HRC, orbital maps and the sun.

The increments travel as the stops' `dead_reckoning` records (a source of rover telemetry,
sources/pds.py, writes them); the tilts as `Traverse.measurements["onboard"]`. The labels' sun
vectors are computed onboard from this same attitude: they are never a sun sighting.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np
from pydantic import Field

from ..graph import factors
from ..graph.keys import X
from ..records import Stop, Traverse
from .base import RowError, Section, StepCounts
from .motion import MotionKind


class OnboardSettings(Section):
    """[estimator.onboard]: the onboard navigation's error, per step between stops (docs/pds.md)."""

    distance_percent: float = Field(3.0, gt=0.0, le=100.0, description="1-sigma of a step's position, per axis, "
                                    "in % of the step's length: Spirit's onboard positions differ from the "
                                    "bundle-adjusted ones by about 3 % of the distance driven (Li et al.)")
    floor_m: float = Field(0.02, gt=0.0, le=10.0, description="the smallest position sigma of a step (a step "
                           "the onboard pose did not move in)")
    rotation_sigma_deg: float = Field(0.2, gt=0.0, le=30.0, description="1-sigma of a step's rotation, per axis "
                                      "(an assumption, not a published figure)")
    tilt_sigma_deg: float = Field(0.2, gt=0.0, le=30.0, description="1-sigma of the onboard tilt at a stop, per "
                                  "axis (an assumption, not a published figure)")


@dataclass(frozen=True)
class OnboardTilt:
    """The rover's up (against gravity) in its body frame at a stop, from its onboard attitude."""

    stop: int
    up_body: np.ndarray  # (3,) unit


def step_covariance(prev_T_curr: np.ndarray, settings: OnboardSettings) -> np.ndarray:
    """A step's 6x6 covariance [rotation, translation] in the current body frame (GTSAM's order)."""
    length = float(np.linalg.norm(np.asarray(prev_T_curr)[:3, 3]))
    sigma_m = max(settings.floor_m, settings.distance_percent / 100.0 * length)
    sigmas = np.array([np.deg2rad(settings.rotation_sigma_deg)] * 3 + [sigma_m] * 3)
    return np.diag(sigmas**2)


def onboard_step_factor(settings: OnboardSettings, key_a: int, key_b: int, a_T_b: gtsam.Pose3,
                        covariance: np.ndarray) -> gtsam.NonlinearFactor:
    """The between factor of an onboard step with this kind's error model (the record's own
    covariance is the source's default model; the settings may differ)."""
    return factors.between(key_a, key_b, a_T_b, step_covariance(a_T_b.matrix(), settings))


class Onboard(MotionKind):
    name = "onboard"
    order = 9
    records = "onboard rover telemetry (a rover product's poses)"
    stop_field = "dead_reckoning"
    builds_motion = "odometry"
    Settings = OnboardSettings
    columns = ("stop", "up_x", "up_y", "up_z")

    @classmethod
    def has_records(cls, traverse: Traverse) -> bool:
        return bool(traverse.measurements.get(cls.name)) and super().has_records(traverse)

    @classmethod
    def to_rows(cls, records: tuple[OnboardTilt, ...]) -> list[tuple[float, ...]]:
        return [(t.stop, *t.up_body) for t in records]

    @classmethod
    def from_rows(cls, rows, traverse: Traverse) -> tuple[OnboardTilt, ...]:
        tilts: list[OnboardTilt] = []
        for line, (stop, *up) in rows:
            if stop != int(stop) or not 0 <= stop < len(traverse.stops):
                raise RowError(line, f"stop {stop:g}: expected a stop index 0..{len(traverse.stops) - 1}")
            if tilts and stop <= tilts[-1].stop:
                raise RowError(line, f"stop {stop:g} does not increase (previous {tilts[-1].stop})")
            up = np.array(up, dtype=float)
            if abs(np.linalg.norm(up) - 1.0) > 1e-3:
                raise RowError(line, f"up ({', '.join(f'{u:g}' for u in up)}) is not a unit vector")
            tilts.append(OnboardTilt(int(stop), up))
        return tuple(tilts)

    def __init__(self, localizer):
        super().__init__(localizer)
        self.settings: OnboardSettings = localizer.estimator.onboard
        self._tilts = {t.stop: t for t in localizer.traverse.measurements.get(self.name, ())}
        self._tilt_model = gtsam.noiseModel.Isotropic.Sigma(2, np.deg2rad(self.settings.tilt_sigma_deg))
        self.used = 0

    def motion_factor(self):
        return partial(onboard_step_factor, self.settings)

    def add(self, stop: Stop, counts: StepCounts) -> None:
        tilt = self._tilts.get(stop.index)
        if tilt is None:
            return
        key = X(stop.index)
        # the vertical where the rover is predicted to be (the site frame is level at its origin only)
        up = self.loc.traverse.origin.up_at(self.loc.smoother.pose(key).translation()[None, :])[0]
        self.loc.smoother.add(gtsam.AttitudeFactorPose3(key, gtsam.Unit3(up), self._tilt_model,
                                                        gtsam.Unit3(tilt.up_body)))
        self.used += 1

    def counters(self) -> dict:
        return {**super().counters(), "onboard_tilts_used": self.used}
