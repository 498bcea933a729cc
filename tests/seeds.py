"""Runs of one scenario over many seeds on every core (test helper): each seed is its own run,
as in one process, so the results do not depend on where they ran."""

from pancam_graph.runtime.processes import cores, process_context
from pancam_graph.solve.pipeline import RunOptions, run_scenario


def _configurations(scenario, seed, configs):
    """One seed's configuration results (in a worker process)."""
    return run_scenario(scenario, RunOptions(seed=seed, configs=configs)).configurations


def over_seeds(scenario, seeds, configs=None) -> list[dict]:
    """Each seed's configuration results, by configuration name, in seed order."""
    from concurrent.futures import ProcessPoolExecutor

    seeds = list(seeds)
    with ProcessPoolExecutor(max_workers=cores(), mp_context=process_context()) as pool:
        return list(pool.map(_configurations, [scenario] * len(seeds), seeds, [configs] * len(seeds)))
