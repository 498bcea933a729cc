"""Measurement kinds: each turns one kind of measurement into factors (see base.Kind). A
configuration is a list of kind names (config.EstimatorConfig.configurations)."""

from __future__ import annotations

from ..records import Traverse
from .base import Kind
from .dead_reckoning import DeadReckoningMotion
from .gps import Gps
from .hrc import Hrc
from .sites import Sites
from .vo import VisualOdometry
from .wheel_slip import WheelSlip

# In the order they are built and called (hrc hooks into sites).
KINDS: dict[str, type[Kind]] = {k.name: k for k in (VisualOdometry, DeadReckoningMotion, WheelSlip, Sites, Hrc, Gps)}


def unavailable(kinds: list[str], traverse: Traverse) -> str | None:
    """Why the traverse cannot feed this configuration, or None."""
    for name in kinds:
        reason = KINDS[name].unavailable(traverse)
        if reason:
            return f"{name}: {reason}"
    return None


__all__ = ["KINDS", "Kind", "unavailable"]
