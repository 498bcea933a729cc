"""The motion between stops, exactly one per configuration: stereo visual odometry, or wheel
odometry + IMU alone (the baseline VO is meant to beat). The between factors themselves come
from the motions estimated once per traverse (solve/pipeline.py); where VO fails, dead
reckoning bridges the step."""

from __future__ import annotations

from typing import ClassVar

from ..records import Traverse
from .base import Kind


class MotionKind(Kind):
    # The Stop field that holds the motion's measurements (empty or None where there are none).
    stop_field: ClassVar[str]

    def __init_subclass__(cls, **kwargs) -> None:
        cls.motion = cls.name
        super().__init_subclass__(**kwargs)

    @classmethod
    def has_records(cls, traverse: Traverse) -> bool:
        return any(getattr(stop, cls.stop_field) for stop in traverse.stops)


class VisualOdometry(MotionKind):
    name = "vo"
    order = 0
    records = "stereo observations"
    stop_field = "stereo"


class DeadReckoningMotion(MotionKind):
    name = "dead_reckoning"
    order = 1
    records = "odometry increments"
    stop_field = "dead_reckoning"
