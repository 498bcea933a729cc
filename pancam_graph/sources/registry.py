"""What a source is to the run: a kind of input, how to recognise it, which options it takes,
and how to load it. Every module of this package that defines `SOURCES` is found, and its
sources join the registry: a new source is one module (plus its test)."""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..config import EstimatorConfig, FrontendConfig, Scenario, SourceOptions
from ..frontend.motion import VoMotions
from ..records import GpsFix, GroundTruth, Stop, Traverse
from ..solve.results import SourceInfo

ProgressCallback = Callable[[str, int, int], None]


@dataclass(frozen=True)
class SourceData:
    """What a source hands the run: the traverse, its truth when there is one, the estimator
    configuration made for it, and its provenance."""

    traverse: Traverse
    truth: GroundTruth | None
    estimator: EstimatorConfig
    seed: int
    info: SourceInfo
    scenario: Scenario | None = None  # simulated sources
    held_out: tuple[GpsFix, ...] = ()  # fixes kept out of every graph, for scoring
    rejected: tuple[str, ...] = ()  # what the reader left out, with reasons
    vo_motions: VoMotions | None = None  # estimated already by the source (image folders with sites)
    load_s: float = 0.0  # what reading the source took (an image source's front-end): part of the run's wall


@dataclass(frozen=True)
class StereoFrames:
    """A stereo image source's frames as the front-end reads them (`bench frontend` times it)."""

    stops: list[Stop]
    read_raw: Callable  # stop k -> its (left, right) images as stored
    size: tuple[int, int]  # (height, width)
    rectify: Callable | None = None  # (pair, stage times) -> the rectified pair; None: stored rectified
    camera_motion: Callable | None = None  # the camera's motion from dead reckoning, for aided tracking


@dataclass(frozen=True)
class Source:
    name: str  # as metrics.json's source.kind says it
    order: int  # recognition order: the first whose `matches` says yes reads the path
    takes: frozenset[str]  # the SourceOptions it accepts
    matches: Callable[[Path], bool]
    load: Callable[[str, SourceOptions, ProgressCallback | None], SourceData]
    describes: str  # what it is, for the message when nothing matches
    # Whether to load this in a process of its own when the run has more than one
    # (processes.call_apart): loading it reports no progress and leaves behind nothing the run
    # needs (a long simulation).
    apart: Callable[[str], bool] = lambda text: False
    # Its stereo frames, when it reads stereo images the front-end tracks (track, bench frontend).
    frames: Callable[[Path], StereoFrames] | None = None
    # The estimator settings it will run with, read without loading it (a scenario's, a folder's
    # manifest): `--configs` is checked against their configurations before a long simulation or
    # front-end. None: they depend on what loading finds (a bag's topics, a PDS folder's
    # cameras), and the names are checked once it is loaded.
    estimator: Callable[[str], EstimatorConfig] | None = None

    @property
    def stereo_images(self) -> bool:
        return self.frames is not None


def frontend_for(options: SourceOptions) -> FrontendConfig | None:
    """An image source's front-end settings: the detector asked for, else the source's own."""
    return FrontendConfig(detector=options.detector) if options.detector else None


def registered() -> list[Source]:
    """Every source of this package's modules, in recognition order."""
    found = []
    for module in pkgutil.iter_modules([str(Path(__file__).parent)]):
        found += getattr(importlib.import_module(f"{__package__}.{module.name}"), "SOURCES", ())
    names = [s.name for s in found]
    if len(set(names)) != len(names):
        raise TypeError(f"two sources share a name: {sorted(names)}")
    return sorted(found, key=lambda s: s.order)
