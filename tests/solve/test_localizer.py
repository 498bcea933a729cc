import gtsam
import numpy as np

from pancam_graph.frontend.motion import motion_between
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.graph.keys import L, X
from pancam_graph.sim import simulate
from pancam_graph.solve.localizer import Localizer


def _solve(scenario, options, seed=4):
    traverse, truth = simulate(scenario, seed)
    vo = StereoVO.for_traverse(traverse, scenario.estimator)
    loc = Localizer(traverse, options, scenario.estimator)
    last = None
    for k, stop in enumerate(traverse.stops):
        if k > 0:
            last = motion_between(vo, traverse.stops[k - 1], stop, last, traverse.wheel_slip)
        loc.step(stop, last)
    return loc, traverse, truth


def test_batch_polish_does_not_increase_graph_error(short_scenario):
    loc, _, truth = _solve(short_scenario, ["vo", "sites", "hrc"])
    loc.smoother.settle()
    incremental = loc.smoother.estimate()
    polished = loc.smoother.batch_polish(incremental)
    graph = loc.smoother.log.all_factors()
    assert graph.error(polished) <= graph.error(incremental) * (1 + 1e-9)
    # and both are close to the truth
    last = len(loc.stops) - 1
    for values in (incremental, polished):
        assert np.linalg.norm(values.atPose3(X(last)).translation() - truth.positions[last]) < 0.5


def test_every_stop_has_a_pose_and_sites_add_landmarks(short_scenario):
    loc, traverse, _ = _solve(short_scenario, ["vo", "sites"])
    assert list(loc.stops) == [s.index for s in traverse.stops]
    assert len(loc.landmarks) > 50
    # tie points only: each landmark in the graph has stereo factors from two sites or more
    poses_seeing = {}
    graph = loc.smoother.log.all_factors()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.GenericStereoFactor3D):
            pose_key, landmark_key = factor.keys()
            poses_seeing.setdefault(landmark_key, set()).add(pose_key)
    assert len(poses_seeing) == len(loc.landmarks)
    assert min(len(poses) for poses in poses_seeing.values()) >= 2


def test_no_false_match_reaches_the_graph_and_true_ties_do(short_scenario):
    """The simulation makes 5 % of panorama matches false (random pixels). The tie gate must keep
    every one of them out of the graph while keeping the true ones in."""
    loc, _, truth = _solve(short_scenario, ["vo", "sites"])
    values = gtsam.Values()
    for k in loc.stops:
        values.insert(X(k), gtsam.Pose3(truth.world_T_body[k]))
    for j in loc.landmarks:
        values.insert(L(j), truth.landmarks[j])
    graph = loc.smoother.log.all_factors()
    pixels_off = np.array([np.linalg.norm(graph.at(i).unwhitenedError(values)) for i in range(graph.size())
                           if isinstance(graph.at(i), gtsam.GenericStereoFactor3D)])
    assert len(pixels_off) > 500
    assert np.sum(pixels_off > 10.0) == 0  # a false match is hundreds of pixels off
    # the true ones: 3 pixel components of 0.3 px noise each
    assert np.sqrt(np.mean(pixels_off**2)) < 0.3 * np.sqrt(3) * 1.15
    assert loc.kind("sites").rejected_ties > 0


def test_a_closed_localizer_is_freed_without_a_garbage_collection(short_scenario):
    """Its kinds (and the factor builders they lend) refer back to it: dropped as it is, only a
    full collection frees it; closed, it goes the moment it is dropped (the run frees each
    configuration's graphs that way, without a collection's walk over the whole process)."""
    import gc
    import weakref

    from pancam_graph.frontend.motion import dead_reckoning_motion

    traverse, _ = simulate(short_scenario, 4)
    vo = StereoVO.for_traverse(traverse, short_scenario.estimator)
    refs = {}
    gc.disable()
    try:
        for kinds in (["dead_reckoning", "wheel_slip"], ["vo", "sites", "hrc"]):
            for close in (False, True):
                loc = Localizer(traverse, kinds, short_scenario.estimator)
                last = None
                for k, stop in enumerate(traverse.stops[:25]):
                    if k > 0:
                        previous = traverse.stops[k - 1]
                        last = (motion_between(vo, previous, stop, last, traverse.wheel_slip) if "vo" in kinds
                                else dead_reckoning_motion(stop, last, traverse.wheel_slip))
                    loc.step(stop, last)
                refs[kinds[-1], close] = weakref.ref(loc)
                if close:
                    loc.close()
                del loc
        alive = {key: ref() is not None for key, ref in refs.items()}
    finally:
        gc.enable()
    assert alive == {("wheel_slip", False): True, ("wheel_slip", True): False,
                     ("hrc", False): True, ("hrc", True): False}
    gc.collect()
    assert all(ref() is None for ref in refs.values())
