"""Whole runs against the issue's thresholds."""

import numpy as np
import pytest
from seeds import over_seeds

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.evaluation.consistency import monte_carlo_summary
from pancam_graph.solve.pipeline import RunOptions, run_scenario

pytestmark = pytest.mark.slow


def test_short_scenario_meets_thresholds(short_run):
    c = short_run.configurations
    assert c["vo"].metrics.relative_closure_pct <= 2.0
    assert c["vo_sites"].metrics.relative_closure_pct <= 0.5
    assert c["full"].metrics.ate_rmse_m < 2.0  # GPS sigma
    assert c["full"].metrics.ate_alignment == "none"
    assert c["vo"].bridged_stops > 0
    assert 0.98 < c["vo"].metrics.length_ratio < 1.02
    assert c["vo_sites"].landmarks > 50
    # GPS evaluation: the estimate sits within the GPS noise of the fixes
    assert c["full"].metrics_vs_gps.average_error_2d_m < 2 * 2.0 * 1.25


def test_twenty_seeds_sites_beat_vo_and_their_covariances_tell_the_truth(short_scenario):
    closures = {"vo": [], "vo_sites": [], "vo_sites_hrc": []}
    bounds = {"vo": [], "vo_sites": []}
    for configurations in over_seeds(short_scenario, range(20), ("vo", "vo_sites", "vo_sites_hrc")):
        for name, values in closures.items():
            values.append(configurations[name].metrics.relative_closure_pct)
        for name, values in bounds.items():
            values.append(configurations[name].consistency)
    mean = {k: float(np.mean(v)) for k, v in closures.items()}
    assert mean["vo"] < 2.0
    assert mean["vo_sites"] < mean["vo"]
    assert mean["vo_sites_hrc"] <= mean["vo_sites"] * 1.05
    # Issue 5: within 20 % of the bound of its own graph, and ANEES inside the 95 % chi-square
    # band of 20 runs (denver_trail with world-frame landmark priors: 2.4x the bound, ANEES 2.8).
    for name, runs in bounds.items():
        summary = monte_carlo_summary(runs)
        assert summary["efficiency"] <= 1.2, name
        assert summary["anees_band"][0] <= summary["anees"] <= summary["anees_band"][1], name


def test_at_sparse_sites_the_hrc_ties_what_the_wac_cannot():
    # Issue 14: sites 75-90 m apart, at the WAC's limit. Over seeds 0-9 the HRC lowers the mean
    # ATE from 0.079 to 0.047 m and wins on every seed; on seeds 0-2 from 0.116 to 0.069 m.
    # The ideal simulator: the realistic profile's ties are the WAC matcher's, and its HRC views
    # are of the landmarks the WAC saw, so at these distances they tie next to nothing
    # (docs/simulation_errors.md, "Not modelled yet").
    scenario = load_scenario(resolve_scenario("sparse_sites"), errors="ideal")
    ate = {"vo_sites": [], "vo_sites_hrc": []}
    for configurations in over_seeds(scenario, range(3), tuple(ate)):
        for name, values in ate.items():
            values.append(configurations[name].metrics.ate_rmse_m)
        counters = configurations["vo_sites_hrc"].counters
        # The gate predicts from the site's own WAC triangulation: it keeps all but the
        # simulated outliers (5 %). Predicting from the earlier site's landmark dropped most.
        seen = counters["hrc_measurements"] + counters["rejected_hrc_measurements"]
        assert counters["hrc_measurements"] > 1000 and counters["rejected_hrc_measurements"] < 0.1 * seen, counters
    assert np.mean(ate["vo_sites_hrc"]) < 0.8 * np.mean(ate["vo_sites"]), ate


def test_900m_vo_only_run_completes_without_indeterminate_system():
    """Cholesky iSAM2 throws 'indeterminate' near stop 400 of this chain; the run must not."""
    scenario = load_scenario(resolve_scenario("denver_trail"))
    result = run_scenario(scenario, RunOptions(seed=0, configs=("dead_reckoning", "vo")))
    assert list(result.configurations) == ["dead_reckoning", "vo"]
    vo = result.configurations["vo"]
    assert len(vo.world_T_body) == len(result.traverse.stops) > 500
    assert vo.metrics.reference_length_m > 850
    assert vo.metrics.relative_closure_pct < 2.0
    assert vo.bridged_stops > 0
    # Dead reckoning alone (wheel slip, gyro drift) is the baseline VO is there to beat: about 5 %
    # closure against VO's 0.25 % on this seed.
    dr = result.configurations["dead_reckoning"]
    assert dr.bridged_stops == len(result.traverse.stops) - 1
    assert dr.metrics.relative_closure_pct > 5.0 * vo.metrics.relative_closure_pct


def test_robust_gps_survives_multipath_outliers():
    scenario = load_scenario(resolve_scenario("gps_multipath"))
    result = run_scenario(scenario, RunOptions(seed=0))
    full = result.configurations["full"]
    assert full.counter("gps_fixes_used") == len(result.traverse.gps_fixes) < len(result.traverse.stops)  # dropouts
    assert full.metrics.ate_rmse_m < 2.0


@pytest.mark.parametrize("name", ["straight_500m"])
def test_other_bundled_scenarios_run(name):
    scenario = load_scenario(resolve_scenario(name))
    result = run_scenario(scenario, RunOptions(seed=0, configs=("vo_sites",)))
    assert result.configurations["vo_sites"].metrics.relative_closure_pct < 0.5
