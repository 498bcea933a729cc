"""A scenario TOML (bundled name or file): simulated traverse and its ground truth."""

from __future__ import annotations

from pathlib import Path

from ..config import load_scenario, resolve_scenario
from ..solve.pipeline import simulated, worth_simulating_apart
from .registry import Source, SourceData


def load(name_or_path: str, seed: int | None = None, errors: str | None = None) -> SourceData:
    scenario = load_scenario(resolve_scenario(name_or_path), errors)
    traverse, truth, resolved, info = simulated(scenario, seed, name_or_path)
    return SourceData(traverse, truth, scenario.estimator, resolved.seed, info, scenario=resolved)


def matches(path: Path) -> bool:
    """A TOML file (there or not: config says which), or a name that is no file (a bundled
    scenario's); an existing file of another kind is not a scenario (an image, a log)."""
    return not path.is_dir() and (path.suffix.lower() == ".toml" or not path.exists())


# Last: what no other source took, when it is a scenario name or TOML file.
SOURCES = (Source("scenario", 100, frozenset({"seed", "errors"}), matches,
                  lambda text, options, progress: load(text, options.seed, options.errors),
                  "a bundled scenario name or a scenario TOML file",
                  lambda text: worth_simulating_apart(load_scenario(resolve_scenario(text))),
                  estimator=lambda text: load_scenario(resolve_scenario(text)).estimator),)
