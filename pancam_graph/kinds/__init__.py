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


def unavailable(kinds: list[str], traverse: Traverse) -> str | None:
    """Why the traverse cannot feed this configuration, or None."""
    for name in kinds:
        reason = KINDS[name].unavailable(traverse)
        if reason:
            return f"{name}: {reason}"
    return None


__all__ = ["KINDS", "Kind", "unavailable"]
