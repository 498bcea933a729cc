"""An observation folder (docs/observation_format.md): what an external front-end hands the back-end."""

from __future__ import annotations

from pathlib import Path

from ..solve.results import SourceInfo
from ..store.observation_folder import is_observation_folder, read_estimator, read_observations
from .registry import Source, SourceData


def matches(path: Path) -> bool:
    return is_observation_folder(path)


def load(path: Path) -> SourceData:
    obs = read_observations(path)
    reference = "truth.kitti of the observation folder" if obs.truth is not None else "none"
    info = SourceInfo("observations", str(path), reference, notes=obs.notes)
    return SourceData(obs.traverse, obs.truth, obs.estimator, obs.seed, info)


SOURCES = (Source("observations", 40, frozenset(), matches, lambda text, options, progress: load(Path(text)),
                  "an observation folder (traverse.toml)", estimator=lambda text: read_estimator(Path(text))),)
