"""Every input kind, one module each, found by one dispatcher: a scenario TOML (simulated), an
observation or image folder, a ROS1/ROS2 bag, a KITTI raw drive or odometry sequence. Each turns
what the user has into a `SourceData` (traverse, optional truth, provenance) for the one run
loop. A module's `SOURCES` say how to recognise it, which options it takes and how to load it
(registry.py): a new source is one module."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from ..config import EstimatorConfig, SourceOptions, bundled_scenarios
from ..errors import ConfigError
from ..runtime.processes import call_apart
from .recorded import is_kitti_drive
from .registry import ProgressCallback, Source, SourceData, registered

SOURCES: list[Source] = registered()


def source_for(text: str) -> Source:
    """The source that reads `text` (a path or a bundled scenario name)."""
    path = Path(text)
    for source in SOURCES:
        if source.matches(path):
            return source
    if path.is_dir() and any(is_kitti_drive(p) for p in path.iterdir() if p.is_dir()):
        drives = sorted(p.name for p in path.iterdir() if is_kitti_drive(p))
        raise ConfigError(f"{path}: a KITTI date folder; give one drive folder inside it ({', '.join(drives)})")
    expected = ", ".join(s.describes for s in SOURCES)
    shadowed, bundled = "", bundled_scenarios()
    if path.is_dir() and text in bundled:
        shadowed = (f" (the folder {text}/ here hides the bundled scenario of that name: give its file, "
                    f"{bundled[text]}, or run from another folder)")
    raise ConfigError(f"{path}: not a source: expected {expected}{shadowed}")


def estimator_before_loading(text: str) -> EstimatorConfig | None:
    """The estimator settings the source `text` will run with (its configurations among them),
    read without loading it; None when only loading it tells (Source.estimator)."""
    source = source_for(text)
    return None if source.estimator is None else source.estimator(text)


def source_kind(text: str) -> str:
    return source_for(text).name


def stereo_image_sources() -> str:
    """The sources with stereo images, in words (for the message when one is needed)."""
    return " or ".join(s.describes for s in SOURCES if s.stereo_images)


def open_source(text: str, options: SourceOptions = SourceOptions(),
                progress: ProgressCallback | None = None, apart: bool = False) -> SourceData:
    """The source named by `text`, loaded (images: the front-end runs over every frame,
    reporting to `progress`). An option the source does not take is an error. `apart`: a
    source that pays for it (`Source.apart`) is loaded in a process of its own (processes.call_apart)."""
    start = time.perf_counter()
    source = source_for(text)
    options.check(source.name, source.takes)
    if apart and source.apart(text):
        data = call_apart(_load, source.name, text, options)
    else:
        data = source.load(text, options, progress)
    return dataclasses.replace(data, load_s=time.perf_counter() - start)


def _load(name: str, text: str, options: SourceOptions) -> SourceData:
    """Source `name`'s data for `text` (in a process of its own: a source's `load` does not pickle)."""
    return next(s for s in SOURCES if s.name == name).load(text, options, None)


__all__ = ["SOURCES", "Source", "SourceData", "SourceOptions", "estimator_before_loading", "open_source",
           "source_for", "source_kind",
           "stereo_image_sources"]
