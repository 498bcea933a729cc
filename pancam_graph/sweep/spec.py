"""A sweep specification (TOML) and the runs it expands to."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, model_validator

from ..config import (
    Scenario,
    _Strict,
    dump_scenario,
    load_scenario,
    load_toml_model,
    resolve_scenario,
    validation_problems,
)
from ..errors import ConfigError
from ..kinds import configuration_problem, scenario_unavailable

RUN_TIMEOUT_S = 3600.0


class SweepVariant(_Strict):
    """A named set of estimator options applied on top of each scenario's own."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,40}$")
    estimator: dict[str, Any] = Field(default_factory=dict)


class SweepSpec(_Strict):
    """Every run of the grid scenarios x rigs x variants x seeds."""

    scenarios: list[str] = Field(min_length=1, description="bundled names or scenario TOML files")
    seeds: int = Field(1, ge=1, le=100_000, description="this many consecutive seeds per combination")
    first_seed: int = Field(0, ge=0)
    rigs: list[str] = Field(default_factory=list, description="rig presets; empty: each scenario's own")
    configs: list[str] | None = Field(None, min_length=1, description="configurations to run (default: all)")
    variants: list[SweepVariant] = Field(default_factory=lambda: [SweepVariant(name="default")], min_length=1)
    timeout_s: float = Field(RUN_TIMEOUT_S, gt=0.0, le=7 * 86400.0, description="a run longer than this is "
                             "stopped and recorded as timed out")

    @model_validator(mode="after")
    def _names_unique(self) -> SweepSpec:
        names = [v.name for v in self.variants]
        if len(set(names)) != len(names):
            raise ValueError(f"variant names must differ: {names}")
        return self


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: a resolved scenario file, a seed and where its results go."""

    scenario: str
    rig: str
    variant: str
    seed: int
    scenario_file: Path
    folder: Path
    configs: tuple[str, ...] | None

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def done(self) -> bool:
        return (self.folder / "metrics.json").is_file()


def load_spec(path: Path) -> SweepSpec:
    return load_toml_model(path, SweepSpec, "sweep specification")


def plan(spec: SweepSpec, out: Path, spec_folder: Path = Path(".")) -> list[SweepRun]:
    """Write each combination's resolved scenario into `out/scenarios/` and list every run. All
    of it is checked first (scenarios, rigs, variants, configuration names), so a bad
    specification writes nothing. A scenario file is found relative to the spec's folder."""
    combinations: list[tuple[str, Scenario, str, SweepVariant]] = []  # label, scenario, rig, variant
    named: dict[str, str] = {}
    for name in spec.scenarios:
        beside = spec_folder / name
        base = load_scenario(beside if name.endswith(".toml") and beside.is_file() else resolve_scenario(name))
        # Runs are filed and reduced by the scenario's name: two files of one name would share
        # their results folders and their rows of the table.
        if base.name in named:
            raise ConfigError(f"sweep: scenarios {named[base.name]} and {name} are both named {base.name!r}; "
                              "give each scenario file its own name")
        named[base.name] = name
        for rig in spec.rigs or [base.rig]:
            for variant in spec.variants:
                scenario = _combined(base, rig, variant, name)
                for config in spec.configs or []:
                    kinds = scenario.estimator.configurations.get(config, config.split("+"))
                    problem = configuration_problem(list(kinds))
                    if problem:
                        raise ConfigError(f"sweep: configs {config!r} ({scenario.name}, variant {variant.name}): "
                                          f"{problem}; defined: {', '.join(scenario.estimator.configurations)}")
                    reason = scenario_unavailable(list(kinds), scenario)
                    if reason:
                        raise ConfigError(f"sweep: configs {config!r} cannot run on {scenario.name} (variant "
                                          f"{variant.name}): {reason}")
                combinations.append((f"{scenario.name}-{rig}-{variant.name}", scenario, rig, variant))
    scenario_folder = Path(out) / "scenarios"
    try:
        scenario_folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot create the sweep folder: {exc.strerror}") from None
    runs = []
    for label, scenario, rig, variant in combinations:
        path = scenario_folder / f"{label}.toml"
        path.write_text(dump_scenario(scenario), encoding="utf-8")
        for seed in range(spec.first_seed, spec.first_seed + spec.seeds):
            runs.append(SweepRun(scenario.name, rig, variant.name, seed, path,
                                 Path(out) / "runs" / f"{label}-seed{seed}",
                                 tuple(spec.configs) if spec.configs else None))
    return runs


def _combined(base: Scenario, rig: str, variant: SweepVariant, name: str) -> Scenario:
    data = base.model_dump(mode="json")
    data["rig"] = rig
    data["estimator"] = {**data["estimator"], **variant.estimator}
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"sweep: scenario {name} with rig {rig} and variant {variant.name}: "
                          f"{validation_problems(exc)}") from None
    return scenario
