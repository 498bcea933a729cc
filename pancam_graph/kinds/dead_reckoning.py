"""Wheel odometry + IMU alone as the motion between stops (the baseline VO is meant to beat)."""

from __future__ import annotations

from ..records import Traverse
from .base import Kind


class DeadReckoningMotion(Kind):
    name = "dead_reckoning"
    order = 1
    motion = "dead_reckoning"

    @staticmethod
    def unavailable(traverse: Traverse) -> str | None:
        if not any(s.dead_reckoning is not None for s in traverse.stops[1:]):
            return "the traverse has no odometry increments"
        return None
