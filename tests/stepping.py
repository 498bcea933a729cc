"""A simulated traverse with its stereo VO motions, for tests that step a Localizer themselves."""

from pancam_graph.frontend.motion import motion_between
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.sim import simulate


def traverse_with_motions(scenario, seed):
    """(traverse, truth, motions): each stop's VO motion from the one before (None at the first)."""
    traverse, truth = simulate(scenario, seed)
    vo = StereoVO.for_traverse(traverse, scenario.estimator)
    motions, last = [None], None
    for k in range(1, len(traverse.stops)):
        last = motion_between(vo, traverse.stops[k - 1], traverse.stops[k], last, traverse.wheel_slip)
        motions.append(last)
    return traverse, truth, motions
