"""A scenario TOML (bundled name or file): simulated traverse and its ground truth."""

from __future__ import annotations

from ..config import load_scenario, resolve_scenario
from ..solve.pipeline import simulated, worth_simulating_apart
from ..solve.results import SourceData
from .registry import Source


def load(name_or_path: str, seed: int | None = None) -> SourceData:
    scenario = load_scenario(resolve_scenario(name_or_path))
    traverse, truth, resolved, info = simulated(scenario, seed, name_or_path)
    return SourceData(traverse, truth, scenario.estimator, resolved.seed, info, scenario=resolved)


# Last: whatever is not a folder of another kind is a scenario name or file (config says which).
SOURCES = (Source("scenario", 100, frozenset({"seed"}), lambda path: not path.is_dir(),
                  lambda text, options, progress: load(text, options.seed),
                  "a bundled scenario name or a scenario TOML file",
                  lambda text: worth_simulating_apart(load_scenario(resolve_scenario(text)))),)
