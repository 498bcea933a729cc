"""A scenario TOML (bundled name or file): simulated traverse and its ground truth."""

from __future__ import annotations

from ..config import Scenario, load_scenario, resolve_scenario
from ..results import SourceInfo
from ..sim import simulate
from .base import SourceData


def scenario_source(scenario: Scenario, seed: int | None = None, path: str | None = None) -> SourceData:
    seed = scenario.seed if seed is None else seed
    traverse, truth = simulate(scenario, seed)
    resolved = scenario.model_copy(update={"seed": seed})  # the results folder's scenario.toml reproduces this run
    info = SourceInfo("scenario", path or scenario.name, "simulation ground truth")
    return SourceData(traverse, truth, scenario.estimator, seed, info, scenario=resolved)


def load(name_or_path: str, seed: int | None = None) -> SourceData:
    return scenario_source(load_scenario(resolve_scenario(name_or_path)), seed, name_or_path)
