"""Who may watch a run stop by stop (the rerun recorder is one): the core knows only this."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from ..frontend.motion import Motion
from ..records import GroundTruth, Stop, Traverse
from .localizer import Localizer, StepResult

if TYPE_CHECKING:
    from .results import RunResult


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
