"""The options that only some sources take (each source says which: sources/): their names,
command-line flags, help and checks, written once. The CLI's flags, its --resume clash check
and a run's reproduce.sh all come from here."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from .errors import ConfigError

DETECTORS = ("gftt", "orb", "sift")


def _option(flag: str, help: str, minimum: float | None = None):
    return field(default=None, metadata={"flag": flag, "help": help, "minimum": minimum})


@dataclass(frozen=True)
class SourceOptions:
    """None: not given. One given to a source that does not take it is an error (`check`)."""

    seed: int | None = _option("--seed", "scenario: override its seed", minimum=0)
    gps_topic: str | None = _option("--gps-topic", "bag: NavSatFix topic (default: the only one)")
    odom_topic: str | None = _option("--odom-topic", "bag: Odometry topic (default: the only one)")
    holdout_every: int | None = _option("--holdout-every", "bag, KITTI: keep every N-th fix out of the graph "
                                        "for scoring (default 5; 0: use all)", minimum=0)
    geoid_height_m: float | None = _option("--geoid-height", "KITTI: geoid height (m) added to OXTS alt")
    detector: str | None = _option("--detector", "image sources: gftt (default), orb or sift")
    skip_bad_frames: bool | None = _option("--skip-bad-frames", "image sources: a missing, truncated or "
                                           "wrong-sized image leaves its stop to the VO bridge (default: stop "
                                           "with a message naming the file)")
    # as text on the command line: LEFT,RIGHT
    stereo_topics: tuple[str, str] | None = _option("--stereo-topics", "bag: LEFT,RIGHT rectified image topics "
                                                    "for stereo VO (CameraInfo beside each: .../camera_info)")

    def __post_init__(self) -> None:
        flags = self.flags()
        for f in fields(self):
            value, minimum = getattr(self, f.name), f.metadata["minimum"]
            if minimum is not None and value is not None and value < minimum:
                raise ConfigError(f"{flags[f.name]} {value}: must be at least {minimum}")
        if self.detector is not None and self.detector not in DETECTORS:
            raise ConfigError(f"--detector {self.detector!r}: expected {', '.join(DETECTORS[:-1])} or {DETECTORS[-1]}")
        if isinstance(self.stereo_topics, str):
            topics = tuple(t.strip() for t in self.stereo_topics.split(",") if t.strip())
            if len(topics) != 2:
                raise ConfigError(f"--stereo-topics {self.stereo_topics!r}: expected LEFT,RIGHT (two image topics)")
            object.__setattr__(self, "stereo_topics", topics)

    @staticmethod
    def flags() -> dict[str, str]:
        """Option name -> its command-line flag."""
        return {f.name: f.metadata["flag"] for f in fields(SourceOptions)}

    @staticmethod
    def help(name: str) -> str:
        return SourceOptions._metadata(name)["help"]

    @staticmethod
    def minimum(name: str) -> float | None:
        return SourceOptions._metadata(name)["minimum"]

    @staticmethod
    def _metadata(name: str):
        return next(f.metadata for f in fields(SourceOptions) if f.name == name)

    def given(self) -> dict[str, object]:
        """The options set (not None), by name."""
        return {name: getattr(self, name) for name in self.flags() if getattr(self, name) is not None}

    def check(self, kind: str, allowed: set[str] | frozenset[str]) -> None:
        for name in self.given():
            if name not in allowed:
                raise ConfigError(f"{self.flags()[name]} does not apply to a {kind} source")
