"""A navigation pair fixed to the body (body_T_nav_left) instead of on the mast."""

from dataclasses import replace

import numpy as np
import pytest

from pancam_graph.sim import simulate
from pancam_graph.solve.pipeline import run
from pancam_graph.solve.results import RunOptions
from pancam_graph.store.observation_folder import read_observations
from pancam_graph.store.observation_writer import write_observations


@pytest.mark.slow
def test_a_body_fixed_pair_is_where_its_transform_puts_it(short_scenario, tmp_path):
    traverse, truth = simulate(short_scenario, 2)
    # The same camera pose given as a body-fixed transform; the mast tilt no longer matters.
    fixed = replace(traverse, traverse_tilt_rad=0.0, body_T_nav_left=traverse.body_T_nav().matrix())
    wrong = replace(traverse, traverse_tilt_rad=0.0)  # the mast, but at the wrong tilt

    def vo(t):
        result = run(t, truth, short_scenario.estimator, 2, RunOptions(configs=("vo",)))
        return result.configurations["vo"]

    mast, body_fixed, mistaken = vo(traverse), vo(fixed), vo(wrong)
    np.testing.assert_array_equal(body_fixed.world_T_body, mast.world_T_body)
    assert mistaken.metrics.ate_rmse_m > 3 * mast.metrics.ate_rmse_m
    # and the observation folder carries it
    write_observations(tmp_path / "obs", fixed, short_scenario.estimator, 2, truth)
    back = read_observations(tmp_path / "obs").traverse
    np.testing.assert_array_equal(back.body_T_nav_left, fixed.body_T_nav_left)
    assert back.traverse_tilt_rad == 0.0
