"""Every input kind, one module each, found by one dispatcher: a scenario TOML (simulated), an
observation folder, a ROS1/ROS2 bag, a KITTI raw drive. Each turns what the user has into a
`SourceData` (traverse, optional truth, provenance) for the one run loop. A KITTI odometry
sequence (stereo images) runs the image front-end first."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..config import FrontendConfig
from ..errors import ConfigError
from ..solve.results import SourceData
from . import image_folder, kitti_odometry, observations, recorded, scenario


@dataclass(frozen=True)
class SourceOptions:
    """Options that only some sources take; one given to a source that does not take it is an error."""

    seed: int | None = None  # scenario
    gps_topic: str | None = None  # rosbag
    odom_topic: str | None = None  # rosbag
    holdout_every: int | None = None  # rosbag, kitti_raw (default 5)
    geoid_height_m: float | None = None  # kitti_raw
    detector: str | None = None  # image sources: gftt, orb, sift
    skip_bad_frames: bool | None = None  # image sources: skip a bad image's stop instead of stopping
    stereo_topics: tuple[str, str] | None = None  # rosbag: left and right image topics (stereo VO)

    def check(self, kind: str, allowed: set[str]) -> None:
        flags = {"seed": "--seed", "gps_topic": "--gps-topic", "odom_topic": "--odom-topic",
                 "holdout_every": "--holdout-every", "geoid_height_m": "--geoid-height", "detector": "--detector",
                 "skip_bad_frames": "--skip-bad-frames", "stereo_topics": "--stereo-topics"}
        for name, flag in flags.items():
            if getattr(self, name) is not None and name not in allowed:
                raise ConfigError(f"{flag} does not apply to a {kind} source")


def source_kind(text: str) -> str:
    path = Path(text)
    if recorded.is_bag(path):
        return "rosbag"
    if recorded.is_kitti_drive(path):
        return "kitti_raw"
    if image_folder.matches(path):
        return "image_folder"
    if observations.matches(path):
        return "observations"
    if kitti_odometry.matches(path):
        return "kitti_odometry"
    if path.is_dir():
        if any(recorded.is_kitti_drive(p) for p in path.iterdir() if p.is_dir()):
            drives = sorted(p.name for p in path.iterdir() if recorded.is_kitti_drive(p))
            raise ConfigError(f"{path}: a KITTI date folder; give one drive folder inside it ({', '.join(drives)})")
        raise ConfigError(f"{path}: not a source: expected an observation folder (traverse.toml), a ROS2 bag "
                          "folder (metadata.yaml), a KITTI raw drive folder (oxts/) or a KITTI odometry "
                          "sequence (calib.txt with image_0/image_1 or image_l/image_r)")
    return "scenario"


def open_source(text: str, options: SourceOptions = SourceOptions(),
                progress: Callable[[str, int, int], None] | None = None) -> SourceData:
    """The source named by `text`: a bundled scenario name or TOML file, an observation folder, a
    ROS bag, a KITTI raw drive folder or a KITTI odometry sequence folder (images: the front-end
    runs over every frame, reporting to `progress`)."""
    kind = source_kind(text)
    if kind == "scenario":
        options.check(kind, {"seed"})
        return scenario.load(text, options.seed)
    if kind == "observations":
        options.check(kind, set())
        return observations.load(Path(text))
    if kind == "kitti_odometry":
        options.check(kind, {"detector", "skip_bad_frames"})
        frontend = FrontendConfig(detector=options.detector) if options.detector else None
        return kitti_odometry.load(Path(text), frontend, progress, bool(options.skip_bad_frames))
    if kind == "image_folder":
        options.check(kind, {"detector", "skip_bad_frames"})
        frontend = FrontendConfig(detector=options.detector) if options.detector else None
        return image_folder.load(Path(text), frontend, progress, bool(options.skip_bad_frames))
    holdout = 5 if options.holdout_every is None else options.holdout_every
    if kind == "rosbag" and options.stereo_topics is not None:
        options.check(kind, {"stereo_topics", "detector", "skip_bad_frames"})
        left, right = options.stereo_topics
        frontend = FrontendConfig(detector=options.detector) if options.detector else None
        return recorded.load_stereo_bag(Path(text), left, right, _info_topic(left), _info_topic(right), frontend,
                                        progress, bool(options.skip_bad_frames))
    if kind == "rosbag":
        options.check(kind, {"gps_topic", "odom_topic", "holdout_every"})
        return recorded.load_bag(Path(text), options.gps_topic, options.odom_topic, holdout)
    options.check(kind, {"geoid_height_m", "holdout_every"})
    return recorded.load_kitti_raw(Path(text), options.geoid_height_m or 0.0, holdout)


def _info_topic(image_topic: str) -> str:
    """The CameraInfo topic beside an image topic: /left/image_rect[/compressed] -> /left/camera_info."""
    parts = [p for p in image_topic.split("/") if p and p != "compressed"]
    return "/" + "/".join(parts[:-1] + ["camera_info"])


__all__ = ["SourceData", "SourceOptions", "open_source", "source_kind"]
