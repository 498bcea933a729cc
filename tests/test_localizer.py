import gtsam
import numpy as np

from pancam_graph.frontend.motion import motion_between
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.graph.keys import X
from pancam_graph.localizer import Localizer, LocalizerOptions
from pancam_graph.sim import simulate


def _solve(scenario, options, seed=4):
    traverse, truth = simulate(scenario, seed)
    vo = StereoVO.for_traverse(traverse, scenario.estimator)
    loc = Localizer(traverse, options, scenario.estimator)
    last = None
    for k, stop in enumerate(traverse.stops):
        if k > 0:
            last = motion_between(vo, traverse.stops[k - 1], stop, last)
        loc.step(stop, last)
    return loc, traverse, truth


def test_batch_polish_does_not_increase_graph_error(short_scenario):
    loc, _, truth = _solve(short_scenario, LocalizerOptions(use_sites=True, use_hrc=True, use_gps=False))
    loc.smoother.settle()
    incremental = loc.smoother.estimate()
    polished = loc.smoother.batch_polish(incremental)
    graph = loc.smoother.graph
    assert graph.error(polished) <= graph.error(incremental) * (1 + 1e-9)
    # and both are close to the truth
    last = len(loc.stops) - 1
    for values in (incremental, polished):
        assert np.linalg.norm(values.atPose3(X(last)).translation() - truth.positions[last]) < 0.5


def test_every_stop_has_a_pose_and_sites_add_landmarks(short_scenario):
    loc, traverse, _ = _solve(short_scenario, LocalizerOptions(use_sites=True, use_hrc=False, use_gps=False))
    assert loc.stops == [s.index for s in traverse.stops]
    assert len(loc.landmarks) > 50
    # tie points only: each landmark in the graph has stereo factors from two sites or more
    poses_seeing = {}
    graph = loc.smoother.graph
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.GenericStereoFactor3D):
            pose_key, landmark_key = factor.keys()
            poses_seeing.setdefault(landmark_key, set()).add(pose_key)
    assert len(poses_seeing) == len(loc.landmarks)
    assert min(len(poses) for poses in poses_seeing.values()) >= 2
