"""What every source hands the run loop."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import EstimatorConfig, Scenario
from ..frontend.motion import VoMotions
from ..records import GpsFix, GroundTruth, Traverse
from ..results import SourceInfo


@dataclass(frozen=True)
class SourceData:
    traverse: Traverse
    truth: GroundTruth | None
    estimator: EstimatorConfig
    seed: int
    info: SourceInfo
    scenario: Scenario | None = None  # simulated sources
    held_out: tuple[GpsFix, ...] = ()  # fixes kept out of every graph, for scoring
    rejected: tuple[str, ...] = ()  # what the reader left out, with reasons
    vo_motions: VoMotions | None = None  # estimated already by the source (image folders with sites)
