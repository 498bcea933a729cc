"""The smoother's window (issue 16): variables leave the Bayes tree once the rover has driven
`window_m` past them, the cost per update stops growing, the estimate stays that of the whole
graph, and checkpoints still resume exactly."""

import pickle

import gtsam
import numpy as np
import pytest
from stepping import traverse_with_motions

from pancam_graph.config import EstimatorConfig, load_scenario, resolve_scenario
from pancam_graph.errors import GraphError
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.frontend.vo_ahead import VoAhead
from pancam_graph.graph import frozen, update_log
from pancam_graph.graph.keys import L, X, subset
from pancam_graph.graph.smoother import RelinearizeThresholds, Smoother
from pancam_graph.kinds.sites import TrackIds
from pancam_graph.runtime import spill
from pancam_graph.solve.localizer import Localizer, smoother_for

WINDOW_M = 60.0  # short_trail is 214 m, with sites about every 40 m


def _traverse(scenario, seed=2):
    return traverse_with_motions(scenario, seed)


@pytest.fixture(scope="module")
def trail(short_scenario):
    return _traverse(short_scenario)


def _localizer(scenario, traverse, kinds, window_m):
    estimator = scenario.estimator.model_copy(update={"window_m": window_m})
    return Localizer(traverse, kinds, estimator, seed=2)


def _solve(loc, traverse, motions, stops=None):
    for stop, motion in list(zip(traverse.stops, motions, strict=True))[:stops]:
        loc.step(stop, motion)
    return loc


def _position_rmse(loc, truth):
    poses = loc.final().world_T_body
    return float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] - truth.positions) ** 2, axis=1))))


@pytest.mark.parametrize("kinds", [["vo", "sites", "hrc"], ["vo", "sites", "hrc", "gps"]])
def test_a_window_shorter_than_the_trail_keeps_the_estimate(short_scenario, trail, kinds):
    traverse, truth, motions = trail
    whole = _solve(_localizer(short_scenario, traverse, kinds, np.inf), traverse, motions)
    windowed = _solve(_localizer(short_scenario, traverse, kinds, WINDOW_M), traverse, motions)
    left = [k for k in windowed.stops if not windowed.smoother.live(X(k))]
    assert len(left) > len(windowed.stops) / 3  # most of the trail left the window
    assert windowed.smoother.isam.getISAM2().size() < 0.6 * whole.smoother.isam.getISAM2().size()
    a, b = _position_rmse(whole, truth), _position_rmse(windowed, truth)
    assert b < 1.15 * a + 0.005, (a, b)  # m
    # a stop that left has its marginal as it left: close to the full smoother's (the later stops add little)
    cov_whole, cov_windowed = whole.position_covariances(), windowed.position_covariances()
    sigma_ratio = np.sqrt(np.trace(cov_windowed, axis1=1, axis2=2) / np.trace(cov_whole, axis1=1, axis2=2))
    assert np.all(np.abs(sigma_ratio - 1.0) < 0.15), sigma_ratio


def test_variables_that_left_take_no_factor_and_have_no_marginal(short_scenario, trail):
    traverse, _, motions = trail
    loc = _solve(_localizer(short_scenario, traverse, ["vo"], WINDOW_M), traverse, motions)
    gone, here = X(0), X(loc.stops[-1])
    assert not loc.smoother.live(gone) and loc.smoother.live(here)
    np.testing.assert_allclose(loc.pose(0)[:3], loc.smoother.frozen.get(gone).reshape(3, 4))  # 3x4 [R | t]
    with pytest.raises(GraphError, match="left the smoother's window"):
        loc.smoother.marginal_covariance(gone)
    with pytest.raises(GraphError, match="left the smoother's window"):
        loc.smoother.add(gtsam.BetweenFactorPose3(gone, here, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1)))


@pytest.mark.parametrize("log", ["in memory", "temporary files", "checkpoint folder"])
def test_a_windowed_run_resumes_from_its_checkpoint_exactly(short_scenario, trail, log, tmp_path, monkeypatch):
    """The update log in memory, spilled to files carried in the pickle, or in files the
    checkpoint refers to (and with them, the variables that left the window and the sites' views
    and landmark tracks in files too): the resumed run is the uninterrupted one to the bit."""
    traverse, _, motions = trail
    kinds = ["vo", "sites", "hrc", "gps"]
    whole = _solve(_localizer(short_scenario, traverse, kinds, WINDOW_M), traverse, motions)
    if log != "in memory":
        monkeypatch.setattr(update_log, "CHUNK_UPDATES", 16)
        monkeypatch.setattr(frozen, "CHUNK_ROWS", 40)
        monkeypatch.setattr(spill, "CHUNK", 30)
        monkeypatch.setattr(TrackIds, "MERGE_AT", 60)
    first = _localizer(short_scenario, traverse, kinds, WINDOW_M)
    if log == "checkpoint folder":
        first.smoother.log.keep_in(tmp_path / "log")
    _solve(first, traverse, motions, stops=70)
    assert not first.smoother.live(X(0))  # marginalization has begun before the checkpoint
    assert first.smoother.log.files == (0 if log == "in memory" else 4)
    assert (first.smoother.frozen.files > 0) == (log != "in memory")
    assert (len(first.kinds["sites"].landmark_ids._filed) > 0) == (log != "in memory")
    saved = pickle.dumps(first)
    for stop, motion in list(zip(traverse.stops, motions, strict=True))[70:]:
        first.step(stop, motion)  # and writes more of its log's files, which the saved state does not know
    resumed = pickle.loads(saved)
    for stop, motion in list(zip(traverse.stops, motions, strict=True))[70:]:
        resumed.step(stop, motion)
    np.testing.assert_array_equal(whole.final().world_T_body, first.final().world_T_body)
    np.testing.assert_array_equal(whole.final().world_T_body, resumed.final().world_T_body)
    np.testing.assert_array_equal(whole.position_covariances(), resumed.position_covariances())
    np.testing.assert_array_equal(whole.final().landmarks, resumed.final().landmarks)
    np.testing.assert_array_equal(whole.tie_links(), resumed.tie_links())
    np.testing.assert_array_equal(whole.stops.to_numpy(), resumed.stops.to_numpy())
    if log == "checkpoint folder":
        assert sorted(p.name for p in (tmp_path / "log").iterdir())[:2] == ["chunk-00000.pkl", "chunk-00001.pkl"]
        (tmp_path / "log" / "chunk-00002.pkl").unlink()
        with pytest.raises(GraphError, match="chunk-00002.pkl: the smoother's update log is missing"):
            pickle.loads(saved)


def test_a_spilled_update_log_reads_back_every_update_in_order(short_scenario, trail, monkeypatch):
    traverse, _, motions = trail
    kinds = ["vo", "sites", "hrc", "gps"]
    in_memory = _solve(_localizer(short_scenario, traverse, kinds, WINDOW_M), traverse, motions)
    monkeypatch.setattr(update_log, "CHUNK_UPDATES", 7)
    spilled = _solve(_localizer(short_scenario, traverse, kinds, WINDOW_M), traverse, motions)
    a, b = in_memory.smoother.log, spilled.smoother.log
    assert a.files == 0 and b.files == b.update_count // 7 > 10 and len(b.tail) == b.update_count % 7
    assert (a.update_count, a.factor_count) == (b.update_count, b.factor_count)
    assert a.update_count >= len(traverse.stops) and a.factor_count == b.all_factors().size()
    values = in_memory.smoother.estimate()
    for x, y in zip(a, b, strict=True):  # CustomFactors remade from their recipes included
        assert x.stamps == y.stamps and list(x.values.keys()) == list(y.values.keys())
        assert x.factors.size() == y.factors.size()
        assert x.factors.error(values) == pytest.approx(y.factors.error(values), rel=1e-12, abs=1e-12)


def test_the_bayes_tree_stops_growing():
    """A 3 km chain of 1 m steps with a 100 m window: the tree holds about the window."""
    smoother = smoother_for(EstimatorConfig(window_m=100.0))
    smoother.insert(X(0), gtsam.Pose3())
    smoother.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    smoother.update()
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.002), np.array([1.0, 0.0, 0.0]))
    sizes = []
    for k in range(1, 3000):
        smoother.clock_m += 1.0
        smoother.insert(X(k), smoother.pose(X(k - 1)).compose(step))
        smoother.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        smoother.update()
        sizes.append(smoother.isam.getISAM2().size())
    assert max(sizes) <= 100 + 50 + 1  # the window moves in steps of half its length
    # a chain: what left is exactly where the whole chain would put it (no later factor moves it)
    expected = gtsam.Pose3()
    for k in range(3000):
        np.testing.assert_allclose(smoother.pose(X(k)).matrix(), expected.matrix(), atol=1e-6)
        expected = expected.compose(step)
    # and each pose that left has its position marginal as it left: in a chain, what the prior
    # and the steps before it give, as GTSAM's batch marginals of the first 300 poses say
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    values.insert(X(0), gtsam.Pose3())
    for k in range(1, 300):
        graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        values.insert(X(k), values.atPose3(X(k - 1)).compose(step))
    batch = gtsam.Marginals(graph, values)
    for k in (0, 1, 150, 299):
        np.testing.assert_allclose(smoother.left_position_covariance(X(k)), batch.marginalCovariance(X(k))[3:, 3:],
                                   rtol=1e-6, atol=1e-12)
    assert smoother.left_position_covariance(X(2999)) is None  # in the window: iSAM2 has its marginal


def test_vo_ahead_in_a_second_process_gives_the_vo_of_this_one(short_scenario, trail):
    traverse, _, _ = trail
    vo = StereoVO.for_traverse(traverse, short_scenario.estimator)
    ahead = VoAhead(traverse, short_scenario.estimator, first=1)
    try:
        for k in range(1, len(traverse.stops)):
            here = vo.estimate(traverse.stops[k - 1].stereo, traverse.stops[k].stereo)
            there = ahead.result(k)
            assert (there.ok, there.inliers, there.reason) == (here.ok, here.inliers, here.reason)
            if here.ok:
                np.testing.assert_allclose(there.prev_T_curr.matrix(), here.prev_T_curr.matrix(), atol=1e-12)
                np.testing.assert_allclose(there.covariance, here.covariance, rtol=1e-9)
    finally:
        ahead.close()


def _tied(loc, a: int, b: int) -> bool:
    """Whether a landmark has views from both site stops a and b."""
    links = loc.tie_links()
    return bool(set(links[links[:, 1] == a, 0]) & set(links[links[:, 1] == b, 0]))


def test_a_site_that_leaves_the_window_at_the_next_site_is_not_searched_for_ties(short_scenario, trail):
    """With a 40 m window (steps of 20 m) the first site leaves in the update that puts the
    second site's pose in the Bayes tree, before the tie gate asks for the two sites' joint
    marginal: no landmark ties them, while later sites still tie. With 50 m they tie."""
    traverse, truth, motions = trail
    assert [s.index for s in traverse.stops if s.is_site][:2] == [0, 40]
    kinds = ["vo", "sites", "gps"]
    narrow = _solve(_localizer(short_scenario, traverse, kinds, 40.0), traverse, motions)
    wider = _solve(_localizer(short_scenario, traverse, kinds, 50.0), traverse, motions)
    assert not _tied(narrow, 0, 40) and narrow.landmarks
    assert _tied(wider, 0, 40)
    assert _position_rmse(narrow, truth) < 0.3  # m


def _chain(factorization: str, n: int = 200, step_sigma_m: float = 1e-6) -> Smoother:
    """A drive of n 1 m steps with micrometre step noise and nothing absolute but the start:
    its uncertainty grows ~1e10 times the step's, past what Cholesky's Hessian can hold."""
    smoother = Smoother(RelinearizeThresholds(0.02, 0.1, 0.05, 2e-5), relinearize_skip=1, window_m=np.inf,
                        wildfire_threshold=0.001,
                        factorization=factorization)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1 * step_sigma_m] * 3 + [step_sigma_m] * 3))
    smoother.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    smoother.insert(X(0), gtsam.Pose3())
    smoother.update()
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.01), np.array([1.0, 0.0, 0.0]))
    for k in range(1, n):
        smoother.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
        smoother.insert(X(k), smoother.pose(X(k - 1)).compose(step))
        smoother.update()
    return smoother


def test_a_failing_cholesky_goes_on_as_qr_to_qr_s_estimate():
    """Configurations with GPS factor with Cholesky (faster); where it fails, the smoother
    replays its updates with QR and goes on: the estimate is QR's own."""
    qr, cholesky = _chain("QR"), _chain("CHOLESKY")
    assert cholesky.factorization == "QR"  # it failed and fell back
    for k in (1, 100, 199):
        np.testing.assert_array_equal(cholesky.pose(X(k)).matrix(), qr.pose(X(k)).matrix())
    assert smoother_for(EstimatorConfig(), with_gps=True).factorization == "CHOLESKY"
    assert smoother_for(EstimatorConfig(), with_gps=False).factorization == "QR"
    assert smoother_for(EstimatorConfig(factorization="qr"), with_gps=True).factorization == "QR"


def test_a_cholesky_found_indeterminate_in_the_back_substitution_goes_on_as_qr(monkeypatch):
    """GTSAM may find a factor indeterminate only when it solves it (getDelta, after the update
    went through: a 100 km mission's `vo_sites` did): with Cholesky, the same fallback to QR as
    a failure in the update."""
    qr = _chain("QR", n=30, step_sigma_m=0.01)
    solve = Smoother._back_substitute

    def indeterminate_once_at_update_20(smoother: Smoother) -> None:
        if smoother.factorization == "CHOLESKY" and smoother.log.update_count == 20:
            raise RuntimeError("Indeterminate linear system detected while working near variable x20")
        solve(smoother)

    monkeypatch.setattr(Smoother, "_back_substitute", indeterminate_once_at_update_20)
    cholesky = _chain("CHOLESKY", n=30, step_sigma_m=0.01)
    assert cholesky.factorization == "QR"
    for k in (1, 20, 29):
        np.testing.assert_array_equal(cholesky.pose(X(k)).matrix(), qr.pose(X(k)).matrix())


def test_the_bound_through_the_window_is_each_stops_information_as_it_left(short_scenario, trail, monkeypatch):
    """At the truth nothing is relinearized, so marginalizing is exact: a stop still in the
    window at the end has the whole graph's bound, and a stop that left has the bound of the
    graph as it stood when it left."""
    traverse, truth, motions = trail
    graph_when_left = {}
    freeze = Smoother._freeze

    def recording_freeze(self, leaving):
        graph_when_left.update(dict.fromkeys(leaving, self.log.factor_count))
        freeze(self, leaving)

    monkeypatch.setattr(Smoother, "_freeze", recording_freeze)
    loc = _solve(_localizer(short_scenario, traverse, ["vo", "sites", "hrc", "gps"], WINDOW_M), traverse, motions)
    values = loc.true_values(truth)
    for k in loc.stops:
        values.insert(X(k), gtsam.Pose3(truth.world_T_body[k]))
    for j in loc.landmarks:
        values.insert(L(j), truth.landmarks[j])
    keys = [X(k) for k in loc.stops]
    bound = loc.smoother.marginals_at(lambda inserted: subset(values, inserted), keys)
    whole = loc.smoother.log.all_factors()

    left = [key for key in keys if key in graph_when_left]
    assert len(left) > len(keys) / 3
    for key in left[:: len(left) // 4] + [k for k in keys if k not in graph_when_left][::40]:
        graph = gtsam.NonlinearFactorGraph()
        for i in range(graph_when_left.get(key, whole.size())):
            graph.add(whole.at(i))
        used = gtsam.Values()
        for k in graph.keyVector():
            used.insert(k, values.atPose3(k) if gtsam.Symbol(k).chr() in (ord("x"), ord("t")) else values.atPoint3(k))
        expected = gtsam.Marginals(graph, used).marginalCovariance(key)
        np.testing.assert_allclose(bound[key], expected, rtol=1e-6, atol=1e-12)


def test_the_calibration_is_relinearized_once_it_moves_past_its_threshold():
    """The stereo pair's calibration error C(0) is linearized where it stands, not where it
    started: its site views' robust weights are taken there (with the scalars' 0.05 it never was;
    docs/simulation_errors.md)."""
    from pancam_graph.graph.keys import C

    smoother = Smoother(RelinearizeThresholds(0.02, 0.1, 0.05, 2e-5), relinearize_skip=1, window_m=np.inf,
                        wildfire_threshold=0.001, factorization="QR")
    smoother.add(gtsam.PriorFactorVector(C(0), np.zeros(6), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    smoother.insert(C(0), np.zeros(6), shared=True)
    smoother.update()
    target = np.array([3e-4, -2e-4, 1e-4, 5e-5, -3e-4, 1e-4])
    smoother.add(gtsam.PriorFactorVector(C(0), target, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    smoother.update()
    smoother.update()  # iSAM2 relinearizes at the update after the one that moved it
    np.testing.assert_allclose(smoother.vector(C(0)), target, atol=1e-7)
    linearized = smoother.isam.getLinearizationPoint().atVector(C(0))
    np.testing.assert_allclose(linearized, target, atol=2e-5)
    assert np.abs(linearized).max() > 1e-4  # it moved from where it started


_HANDED: list[gtsam.Values] = []  # what the chain's error functions were handed, in order


def _recording_step(key_a: int, key_b: int) -> gtsam.CustomFactor:
    """A between factor of a unit step in x, in Python, that keeps the Values it is handed."""
    step = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))

    def error(factor, values, jacobians):
        _HANDED.append(values)
        a, b = values.atPose3(key_a), values.atPose3(key_b)
        if jacobians is not None:
            jacobians[0], jacobians[1] = np.zeros((6, 6)), np.zeros((6, 6))
            return gtsam.Pose3.Logmap(step.between(a.between(b, jacobians[0], jacobians[1])))
        return gtsam.Pose3.Logmap(step.between(a.between(b)))

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(6, 0.01), [key_a, key_b], error)


def test_python_factors_are_handed_the_linearization_point_itself_not_a_copy():
    """pybind11 copies the Values it hands a Python factor (the whole window, every time)
    unless a Python object already wraps it: the smoother holds iSAM2's, in its updates, after a
    replay and in the bound's replay alike (smoother.py, the held linearization point)."""
    smoother = smoother_for(EstimatorConfig(window_m=10.0))
    smoother.insert(X(0), gtsam.Pose3())
    smoother.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    smoother.update()

    def drive(smoother, stops):
        for k in stops:
            smoother.clock_m += 1.0
            smoother.insert(X(k), gtsam.Pose3(gtsam.Rot3(), np.array([k + 0.3, 0.2, 0.0])))  # off: relinearized
            smoother.add(_recording_step(X(k - 1), X(k)), rebuild=(_recording_step, (X(k - 1), X(k))))
            smoother.update()

    _HANDED.clear()
    drive(smoother, range(1, 25))
    assert len(_HANDED) > 24 and all(v is smoother._linearization_point for v in _HANDED)
    resumed = pickle.loads(pickle.dumps(smoother))
    _HANDED.clear()
    drive(resumed, range(25, 30))
    assert len(_HANDED) > 5 and all(v is resumed._linearization_point for v in _HANDED)
    _HANDED.clear()

    def on_the_line(keys):
        values = gtsam.Values()
        for key in keys:
            values.insert(key, gtsam.Pose3(gtsam.Rot3(), np.array([gtsam.Symbol(key).index(), 0.0, 0.0])))
        return values

    resumed.marginals_at(on_the_line, [X(29)])
    assert len(_HANDED) > 5 and all(v is _HANDED[0] for v in _HANDED)


def test_released_solver_lets_isam2_go():
    """The held linearization point keeps its iSAM2 alive: releasing the solver must let go of
    both, or the bound's replay builds its window on top of the live one."""
    import weakref

    smoother = smoother_for(EstimatorConfig(window_m=10.0))
    smoother.insert(X(0), gtsam.Pose3())
    smoother.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    smoother.update()
    isam = weakref.ref(smoother.isam)
    smoother.release_solver()
    assert isam() is None


def test_a_landmark_that_outlives_its_gating_site_takes_no_more_views():
    """A landmark tied as its first site was leaving the window stays after it (Smoother.insert):
    a later site's view of it cannot be gated against a site that has no marginal any more, and
    is left out (realistic short_trail seed 1 with a 60 m window: the run stopped at stop 83 of 142
    with "x38 left the smoother's window" before)."""
    scenario = load_scenario(resolve_scenario("short_trail"))
    traverse, truth, motions = _traverse(scenario, seed=1)
    windowed = _solve(_localizer(scenario, traverse, ["vo", "sites"], WINDOW_M), traverse, motions)
    whole = _solve(_localizer(scenario, traverse, ["vo", "sites"], np.inf), traverse, motions)
    a, b = _position_rmse(whole, truth), _position_rmse(windowed, truth)
    assert b < 1.15 * a + 0.005, (a, b)  # m, as the ideal trail's window
