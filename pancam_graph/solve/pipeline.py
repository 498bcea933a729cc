"""The run loop: estimate the motion of every stop once, feed every configuration's localizer
stop by stop, then evaluate each against the reference, the GPS fixes and the held-out fixes
(group.py); the configurations in groups side by side when the run may use more processes
(side_by_side.py)."""

from __future__ import annotations

import difflib
import time
from dataclasses import replace

from ..config import EstimatorConfig, Scenario
from ..errors import ConfigError
from ..frontend.motion import VoMotions
from ..kinds import KINDS, configuration_problem, relative_cost, unavailable, uses_vo
from ..records import GpsFix, GroundTruth, Traverse
from ..runtime.memory import peak_rss_mb
from ..runtime.processes import call_apart
from ..sim import simulate
from .group import GroupJob, ProgressCallback, localize_group
from .listener import RunListener
from .results import ConfigurationResult, RunOptions, RunResult, SourceInfo
from .side_by_side import MemoryWatch, localize_side_by_side
from .state import Checkpoints, RunState


def select_configurations(estimator: EstimatorConfig, traverse: Traverse, requested: tuple[str, ...] | None
                          ) -> tuple[dict[str, list[str]], dict[str, str]]:
    """(name -> kinds to run, name -> why a defined configuration is skipped). Without a request,
    every defined configuration the traverse can feed; a requested one is a defined name or kinds
    joined by '+' (e.g. vo+gps), and one the traverse cannot feed is an error."""
    defined = estimator.configurations
    if requested is None:
        chosen, skipped = {}, {}
        for name, kinds in defined.items():
            reason = unavailable(kinds, traverse)
            if reason:
                skipped[name] = reason
            else:
                chosen[name] = list(kinds)
        if not chosen:
            raise ConfigError(f"{traverse.name}: no configuration can run on this traverse: "
                              + "; ".join(f"{n}: {r}" for n, r in skipped.items()))
        check_traverse(chosen, traverse)
        return chosen, skipped
    chosen = {}
    for name, kinds in configuration_kinds(estimator, requested).items():
        reason = unavailable(kinds, traverse)
        if reason:
            raise ConfigError(f"--configs {name}: this traverse cannot feed it ({reason})")
        chosen[name] = kinds
    check_traverse(chosen, traverse)
    return chosen, {}


def configuration_kinds(estimator: EstimatorConfig, requested: tuple[str, ...]) -> dict[str, list[str]]:
    """name -> kinds of each requested configuration: a name the estimator defines or kinds
    joined by '+'. What the names alone can tell, before the traverse is there (a long
    simulation or front-end need not run for a typo)."""
    defined = estimator.configurations
    chosen = {}
    for name in requested:
        kinds = list(defined[name]) if name in defined else name.split("+")
        problem = configuration_problem(kinds)
        if problem:
            close = difflib.get_close_matches(name, list(defined), n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            raise ConfigError(f"--configs {name}: {problem}; {hint}defined configurations: {', '.join(defined)}")
        chosen[name] = kinds
    return chosen


def check_traverse(chosen: dict[str, list[str]], traverse: Traverse) -> None:
    """Every chosen kind's rules for the traverse's records (Kind.check_traverse), once each."""
    for name in KINDS:
        if any(name in kinds for kinds in chosen.values()):
            KINDS[name].check_traverse(traverse)


def run_scenario(scenario: Scenario, options: RunOptions = RunOptions(), progress: ProgressCallback | None = None,
        listener: RunListener | None = None) -> RunResult:
    """Simulate the scenario and run every configuration on it (with more than one process,
    the simulation in a process of its own: processes.call_apart)."""
    start = time.perf_counter()
    if options.processes > 1 and worth_simulating_apart(scenario):
        traverse, truth, resolved, info = call_apart(simulated, scenario, options.seed)
    else:
        traverse, truth, resolved, info = simulated(scenario, options.seed)
    return run(traverse, truth, scenario.estimator, resolved.seed, options, progress, listener,
                        source=info, scenario=resolved, started=start)


# A scenario at least this long is simulated in a process of its own when the run has more than
# one: that process waits about 1 s for the fork server's imports, which a short traverse does not
# repay, and gives back what the simulation leaves in memory (docs/performance.md).
SIMULATE_APART_M = 3000.0


def worth_simulating_apart(scenario: Scenario) -> bool:
    return scenario.path.length_m >= SIMULATE_APART_M


def simulated(scenario: Scenario, seed: int | None = None, name: str | None = None
              ) -> tuple[Traverse, GroundTruth, Scenario, SourceInfo]:
    """The scenario's traverse and truth for `seed` (default: its own), the scenario resolved
    with that seed (its scenario.toml reproduces the run) and the source's provenance."""
    seed = scenario.seed if seed is None else seed
    traverse, truth = simulate(scenario, seed)
    info = SourceInfo("scenario", name or scenario.name, "simulation ground truth")
    return traverse, truth, scenario.model_copy(update={"seed": seed}), info


def run(
    traverse: Traverse,
    truth: GroundTruth | None,
    estimator: EstimatorConfig,
    seed: int,
    options: RunOptions = RunOptions(),
    progress: ProgressCallback | None = None,
    listener: RunListener | None = None,
    source: SourceInfo | None = None,
    scenario: Scenario | None = None,
    held_out: tuple[GpsFix, ...] = (),
    started: float | None = None,
    save: Checkpoints | None = None,
    resume: list[RunState] | None = None,
    vo_motions: VoMotions | None = None,
) -> RunResult:
    """Estimate the motion of every stop once, feed every configuration's localizer stop by
    stop, then evaluate each against the reference (when there is one) and GPS. At every
    checkpoint `save` gets the state of a group of configurations; a run given `resume` (the
    groups' last states) goes on from them. `vo_motions`: the stops' VO motions when a source
    has estimated them already (with this estimator configuration).

    With `options.processes` > 1 and no listener, the configurations run in groups side by
    side in that many worker processes (side_by_side.py); a listener watches every localizer
    at every stop, so with one they all stay in this process."""
    start = time.perf_counter() if started is None else started
    source = source or SourceInfo("traverse", traverse.name, "truth" if truth is not None else "none")
    chosen, skipped = select_configurations(estimator, traverse, options.configs)
    n = len(traverse.stops)
    known = vo_motions if vo_motions is not None and vo_motions.estimator == estimator and len(
        vo_motions.motions) == n else None
    if resume:
        start -= max(state.elapsed_s for state in resume)
    groups = configuration_groups(chosen, options, listener, resume, n)
    if listener is not None and len(groups) > 1:
        raise ConfigError(f"this run was checkpointed in {len(groups)} groups of configurations side by side; a "
                          "listener (the live view) needs them all in one process: go on without it")
    job = GroupJob(traverse, truth, estimator, seed, options, tuple(held_out), groups[0])
    memory = MemoryWatch()
    if len(groups) > 1 and options.processes > 1:
        outcomes = localize_side_by_side(job, groups, resume, known, save, progress, start, memory)
    else:  # one group, or the groups of a resumed run one after another
        outcomes = [localize_group(replace(job, configs=configs), resume[g] if resume and g < len(resume) else None,
                              known, save.part(g) if save is not None and len(groups) > 1 else save, progress,
                              listener, start) for g, configs in enumerate(groups)]
    results: dict[str, ConfigurationResult] = {}
    for outcome in outcomes:
        results.update(outcome.results)
    results = {name: results[name] for name in chosen}
    # the motions the VO configurations were fed (a group without any was fed dead reckoning)
    motions = next((o.motions for o in outcomes if any(uses_vo(chosen[c]) for c in o.results)), outcomes[0].motions)
    result = RunResult(source, scenario, estimator, options, seed, traverse, truth, tuple(held_out),
                       motions, results, skipped, time.perf_counter() - start,
                       max(o.vo_s for o in outcomes), [o.process for o in outcomes],
                       memory.peak_mb if memory.peak_mb is not None else peak_rss_mb())
    if listener is not None:
        listener.finish(result)
    return result


def configuration_groups(chosen: dict[str, list[str]], options: RunOptions, listener: RunListener | None,
                         resume: list[RunState] | None, n: int) -> list[dict[str, list[str]]]:
    """The configurations split into groups that run side by side: a resumed run keeps its
    groups (configurations that no saved group holds start anew in one more). Otherwise the
    configurations without VO make one group, which starts while the VO is estimated, and the
    others are spread over `options.processes` groups of about equal cost; all in one group
    when a listener watches them all or the traverse is too short to pay for the processes."""
    if resume:
        held = [{name: chosen[name] for name in state.localizers} for state in resume]
        rest = {name: kinds for name, kinds in chosen.items() if not any(name in g for g in held)}
        return held + ([rest] if rest else [])
    if min(options.processes, len(chosen)) <= 1 or listener is not None or n < options.side_by_side_min_stops:
        return [dict(chosen)]
    with_vo = {name: kinds for name, kinds in chosen.items() if uses_vo(kinds)}
    without = {name: kinds for name, kinds in chosen.items() if not uses_vo(kinds)}
    if not with_vo:
        return _balanced(without, options.processes)
    return ([without] if without else []) + _balanced(with_vo, options.processes)


def _balanced(chosen: dict[str, list[str]], count: int) -> list[dict[str, list[str]]]:
    """Up to `count` groups of about equal cost: the dearest configuration first, each to the
    group with the least so far."""
    loads = [0.0] * min(count, len(chosen))
    groups: list[dict[str, list[str]]] = [{} for _ in loads]
    for name in sorted(chosen, key=lambda c: -relative_cost(chosen[c])):
        g = loads.index(min(loads))
        groups[g][name] = chosen[name]
        loads[g] += relative_cost(chosen[name])
    return groups
