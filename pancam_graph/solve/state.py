"""What a group of configurations has done so far (saved at checkpoints, resumed from), and what
saves it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from ..frontend.motion import Motions
from ..records import GroundTruth, Traverse
from .localizer import Localizer
from .step_table import StepTable

CHECKPOINT_EVERY_STOPS = 25  # checkpoints (and listeners' flushes) at every site and at least this often
# ... and at the first stop after this many seconds of work since the last (slow stops: a Mars
# site's registrations, an image run), so a kill loses at most about this much
CHECKPOINT_EVERY_S = 60.0


@dataclass
class RunState:
    """All a group of configurations has done before stop `next_stop` (a run in one process:
    every configuration): their graphs and bookkeeping, the motions and the per-stop results.
    Saved at checkpoints; a run given its groups' states goes on from them and ends with the
    same estimate as one that was never stopped."""

    next_stop: int
    localizers: dict[str, Localizer]
    motions: Motions
    dr_motions: Motions
    steps: dict[str, StepTable]
    vo_s: float = 0.0
    elapsed_s: float = 0.0  # wall time spent on the run before this state
    memory_mb: list[tuple[int, float]] = field(default_factory=list)  # (stop, the process's resident MB) at checkpoints
    peak_pss_mb: float = 0.0  # the process's largest proportional set size seen at checkpoints


class Checkpoints(Protocol):
    """Saves a group's state at a checkpoint (store/checkpoint.CheckpointWriter)."""

    def __call__(self, state: RunState) -> None: ...

    def part(self, index: int) -> Checkpoints:
        """The writer of group `index` when groups run side by side."""

    def refer_to(self, traverse: Traverse, truth: GroundTruth | None) -> None:
        """Name these (a group process's own) in the states instead of saving them."""

    def log_folder(self, configuration: str) -> Path:
        """Where a configuration's smoother keeps its update log (the saved states refer to it)."""
