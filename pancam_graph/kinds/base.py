"""What a measurement kind is to the localizer: hooks around one stop's iSAM2 update.

A kind owns its factor builder, its gate, its counters and the metrics it reports. The localizer
calls, for every stop: `pose_times` (measurements between the previous stop and this one that
need a pose of their own), `add` (this stop's factors, before the update), `after_update`; and
`counters` once at the end.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import gtsam

from ..records import GroundTruth, Stop, Traverse

if TYPE_CHECKING:
    from ..localizer import Localizer, StepCounts


_REGISTRY: dict[str, type[Kind]] = {}


def registered() -> dict[str, type[Kind]]:
    """Every kind by name, in build order."""
    return dict(sorted(_REGISTRY.items(), key=lambda item: item[1].order))


class Kind:
    name: ClassVar[str]
    order: ClassVar[int]  # build and call order: a kind that hooks into another comes after it

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if cls.name in _REGISTRY:
            raise TypeError(f"two measurement kinds are named {cls.name!r}")
        _REGISTRY[cls.name] = cls

    def __init__(self, localizer: Localizer):
        self.loc = localizer

    @staticmethod
    def unavailable(traverse: Traverse) -> str | None:
        """Why this traverse cannot feed the kind, or None."""
        return None

    def pose_times(self, prev: Stop, stop: Stop) -> list[float]:
        """Times strictly inside the drive from `prev` to `stop` at which this kind needs a pose."""
        return []

    def add(self, stop: Stop, counts: StepCounts) -> None:
        """This stop's factors (before the stop's update)."""

    def after_update(self, stop: Stop, counts: StepCounts) -> None:
        """Checks against the updated estimate."""

    def true_values(self, truth: GroundTruth, values: gtsam.Values) -> bool:
        """Insert the true values of this kind's own variables (for the CRLB); False when unknown."""
        return True

    def finish(self) -> None:
        """The traverse is over: anything left to account for."""

    def counters(self) -> dict[str, int | float | list[str]]:
        """What this kind did over the whole traverse, for metrics.json."""
        return {}
