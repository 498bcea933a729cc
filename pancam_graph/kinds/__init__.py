"""Measurement kinds: each turns one kind of measurement into factors (see base.Kind). A
configuration is a list of kind names (config.EstimatorConfig.configurations).

Every module of this package is imported here, and every `Kind` subclass in it registers
itself: a new kind is one module (plus its test), nothing else to edit.
"""

from __future__ import annotations

import importlib
import pkgutil

from ..records import Traverse
from .base import Kind, registered

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

# In the order they are built and called (a kind may hook into one built before it).
KINDS: dict[str, type[Kind]] = registered()


# Every kind's per-stop counters with their defaults, in registry order: steps.csv's columns.
STEP_COUNTERS: dict[str, float | None] = {name: default for kind in KINDS.values()
                                          for name, default in kind.step_counters.items()}
# Every kind's whole-traverse counters with their defaults: every configuration reports them all.
COUNTER_DEFAULTS: dict[str, float | list] = {name: default for kind in KINDS.values()
                                             for name, default in kind.counter_defaults.items()}


def uses_vo(kinds: list[str]) -> bool:
    """The configuration's motion is the stereo VO's."""
    return any(KINDS[k].motion == "vo" for k in kinds)


def absolute(kinds: list[str]) -> bool:
    """The configuration has an absolute position (GPS): its estimate is in the world frame as it
    stands, and its uncertainty is bounded."""
    return any(KINDS[k].absolute for k in kinds)


def relative_cost(kinds: list[str]) -> float:
    """A configuration's time per stop relative to plain VO's (each kind's `cost`): what
    balances the groups of configurations run side by side."""
    return 1.0 + sum(KINDS[k].cost for k in kinds)


def stop_records(kinds: list[str]) -> set[str]:
    """The stops' image records a configuration reads besides the stereo VO's (Kind.stop_records)."""
    return set().union(*(KINDS[k].stop_records for k in kinds))


def configuration_problem(kinds: list[str]) -> str | None:
    """Why a list of kinds is not a configuration, or None."""
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        return f"unknown kind {unknown[0]!r} (kinds: {', '.join(KINDS)})"
    motions = [k for k in kinds if KINDS[k].motion is not None]
    if len(motions) != 1:
        return "needs exactly one motion kind, " + " or ".join(repr(k) for k, c in KINDS.items() if c.motion)
    for k in kinds:
        for need, why in KINDS[k].needs.items():
            if need not in kinds:
                return f"{k!r} needs {need!r} ({why})"
    if len(set(kinds)) != len(kinds):
        return "a kind is listed twice"
    return None


def scenario_unavailable(kinds: list[str], scenario) -> str | None:
    """Why a simulation of the scenario cannot feed this configuration, or None (before simulating)."""
    for name in kinds:
        reason = KINDS[name].scenario_unavailable(scenario)
        if reason:
            return f"{name}: {reason}"
    return None


def unavailable(kinds: list[str], traverse: Traverse) -> str | None:
    """Why the traverse cannot feed this configuration, or None."""
    for name in kinds:
        reason = KINDS[name].unavailable(traverse)
        if reason:
            return f"{name}: {reason}"
    return None


__all__ = ["COUNTER_DEFAULTS", "KINDS", "STEP_COUNTERS", "Kind", "absolute", "configuration_problem", "relative_cost",
           "scenario_unavailable", "stop_records", "unavailable", "uses_vo"]
