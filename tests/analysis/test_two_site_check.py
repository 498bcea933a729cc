"""The dissertation's two-site setting simulated and adjusted (analysis/two_site_check.py)
against what the closed form predicts."""

import numpy as np
import pytest

from pancam_graph.analysis.design import AnalysisRig, Assumptions, max_site_spacing, optimal_fov
from pancam_graph.analysis.two_site_check import two_site_monte_carlo


@pytest.mark.parametrize("name", ["exomars", "mer_navcam", "mer_pancam"])
def test_the_simulated_adjustment_gives_the_rigid_closed_forms_error_at_table_3_2s_spacing(name):
    """At the spacing `analyze` reports for 1 %, 300 noisy two-site adjustments scatter as the
    closed form's rigid transform predicts (within the trials' 95 % interval), with no bias; the
    dissertation's 4-parameter transform (1 % there) lies outside that interval: it estimates a
    scale the stereo adjustment does not have."""
    rig, a = AnalysisRig.preset(name), Assumptions()
    fov = optimal_fov(rig, a)
    check = two_site_monte_carlo(rig, a, max_site_spacing(rig, a, fov), fov, trials=300, seed=1)
    low, high = check.simulated_interval
    assert low <= check.predicted_rigid <= high
    assert check.predicted_dissertation == pytest.approx(a.relative_error_target, rel=1e-3)
    assert check.predicted_dissertation > high
    spread = check.errors_m.std(axis=0) / np.sqrt(check.trials)
    assert np.all(np.abs(check.errors_m.mean(axis=0)) < 3.5 * spread)
