"""Stereo visual odometry as the motion between stops: the between factors come from the VO
estimated once per traverse (pipeline), bridged by dead reckoning where VO fails."""

from __future__ import annotations

from ..records import Traverse
from .base import Kind


class VisualOdometry(Kind):
    name = "vo"
    order = 0
    motion = "vo"

    @staticmethod
    def unavailable(traverse: Traverse) -> str | None:
        if not any(len(s.stereo) for s in traverse.stops):
            return "the traverse has no stereo observations"
        return None
