"""Configurations in groups side by side (one process each) give exactly the estimate of a run
in one process, and a run checkpointed in groups goes on from each group's last state to that
same estimate."""

import numpy as np
import pytest

from pancam_graph.solve.pipeline import configuration_groups, run, select_configurations
from pancam_graph.solve.results import RunOptions
from pancam_graph.sources import open_source
from pancam_graph.store.checkpoint import CheckpointWriter, RunInputs, read_checkpoint

pytestmark = pytest.mark.slow

SIDE_BY_SIDE = RunOptions(processes=2, side_by_side_min_stops=0)


@pytest.fixture(scope="module")
def short_trail():
    return open_source("short_trail")


def _run(data, options, **kwargs):
    return run(data.traverse, data.truth, data.estimator, data.seed, options, **kwargs)


def _assert_same(a, b):
    assert list(a.configurations) == list(b.configurations)
    for name in a.configurations:
        x, y = a.configurations[name], b.configurations[name]
        np.testing.assert_array_equal(x.world_T_body, y.world_T_body, err_msg=name)
        np.testing.assert_array_equal(x.position_covariance, y.position_covariance, err_msg=name)
        np.testing.assert_array_equal(x.landmark_positions, y.landmark_positions, err_msg=name)
        assert x.consistency == y.consistency, name


def _feedable(data) -> dict:
    """The configurations a run of `data` chooses (those its traverse can feed)."""
    return select_configurations(data.estimator, data.traverse, None)[0]


def test_groups_balance_the_configurations_by_cost(short_trail):
    chosen = _feedable(short_trail)
    groups = configuration_groups(chosen, SIDE_BY_SIDE, None, None, 1000)
    # the configurations without VO start while it is estimated; the others in groups of equal cost
    assert [list(g) for g in groups] == [["dead_reckoning", "dead_reckoning_gps"], ["vo_sites", "full"],
                                         ["vo_sites_hrc", "vo"]]
    # a listener watches every localizer, and a short traverse does not pay for the processes
    assert len(configuration_groups(chosen, SIDE_BY_SIDE, object(), None, 1000)) == 1
    assert len(configuration_groups(chosen, RunOptions(processes=2), None, None, 299)) == 1


def test_side_by_side_equals_one_process(short_trail):
    one = _run(short_trail, RunOptions())
    two = _run(short_trail, SIDE_BY_SIDE)
    _assert_same(one, two)
    assert [p.label for p in one.processes] == ["run"]
    assert [p.configurations for p in two.processes] == [("dead_reckoning", "dead_reckoning_gps"),
                                                         ("vo_sites", "full"), ("vo_sites_hrc", "vo")]
    assert all(p.memory_mb and p.seconds > 0 for p in two.processes)
    assert len({p.pid for p in two.processes}) == 2  # three groups, one worker per core
    # the run's processes at once: more than the largest worker's own peak, less than all peaks summed
    peaks = {p.pid: max(mb for _, mb in p.memory_mb) for p in two.processes}
    assert max(peaks.values()) < two.peak_memory_mb
    np.testing.assert_array_equal([m.prev_T_curr.matrix() for m in one.motions[1:]],
                                  [m.prev_T_curr.matrix() for m in two.motions[1:]])


def test_a_run_checkpointed_in_groups_resumes_to_the_same_estimate(short_trail, tmp_path):
    whole = _run(short_trail, SIDE_BY_SIDE)
    writer = CheckpointWriter(tmp_path, RunInputs(short_trail, SIDE_BY_SIDE), min_interval_s=0)
    _run(short_trail, SIDE_BY_SIDE, save=writer)
    inputs, states = read_checkpoint(tmp_path)  # the last states saved before the end: as if killed there
    groups = configuration_groups(_feedable(short_trail), SIDE_BY_SIDE, None, None, 1000)
    assert [list(s.localizers) for s in states] == [list(g) for g in groups]
    n = len(short_trail.traverse.stops)
    assert all(0 < s.next_stop < n for s in states)
    assert writer.saved_stops == [s.next_stop for s in states]
    resumed = _run(inputs.data, inputs.options, resume=states)
    _assert_same(whole, resumed)
    # and in this process, one group after the other
    inputs, states = read_checkpoint(tmp_path)
    _assert_same(whole, _run(inputs.data, RunOptions(), resume=states))


def _same_frames(a, b) -> bool:
    """Panorama or HRC frames equal, their arrays compared as arrays."""
    def flat(frame):
        obs = getattr(frame, "observations", frame)
        arrays = [np.asarray(getattr(obs, f)).tolist() for f in ("track_ids", "uvv", "uv") if hasattr(obs, f)]
        return [frame.pan_rad, frame.tilt_rad, *arrays]
    return len(a) == len(b) and all(flat(x) == flat(y) for x, y in zip(a, b, strict=True))


def test_a_group_is_sent_only_the_image_records_it_reads(short_trail, tmp_path):
    """The motions are given to a worker, so it gets no stereo; panoramas and HRC frames only
    with the kinds that read them, in a file read a stop at a time. (That the estimates do not
    change is the test above.)"""
    from pancam_graph.kinds import stop_records
    from pancam_graph.solve.group import GroupJob
    from pancam_graph.solve.side_by_side import _job_of
    from pancam_graph.solve.stop_records import StopRecords

    traverse = short_trail.traverse
    job = GroupJob(traverse, short_trail.truth, short_trail.estimator, 0, SIDE_BY_SIDE, (), {})
    sites = [k for k, s in enumerate(traverse.stops) if s.is_site]
    assert sites and all(traverse.stops[k].panorama and traverse.stops[k].hrc for k in sites)
    group = _job_of(job, {"vo_sites_hrc": ["vo", "sites", "hrc"]})
    assert all(len(s.stereo.track_ids) == 0 and not s.panorama and not s.hrc for s in group.traverse.stops)
    assert group.traverse.gps_fixes == traverse.gps_fixes
    assert [s.dead_reckoning for s in group.traverse.stops] == [s.dead_reckoning for s in traverse.stops]

    assert stop_records(["dead_reckoning", "gps"]) == set()  # the dead-reckoning group gets no file
    with_sites = StopRecords.write(tmp_path / "sites", traverse, stop_records(["vo", "sites"]))
    with_hrc = StopRecords.write(tmp_path / "hrc", traverse, stop_records(["vo", "sites", "hrc"]))
    assert sorted(with_sites.offsets) == sorted(with_hrc.offsets) == sites
    for k in sites:
        bare = group.traverse.stops[k]
        a, b = with_sites.attach(k, bare), with_hrc.attach(k, bare)
        assert _same_frames(a.panorama, traverse.stops[k].panorama) and not a.hrc
        assert _same_frames(b.panorama, traverse.stops[k].panorama) and _same_frames(b.hrc, traverse.stops[k].hrc)
        assert a.index == k and a.dead_reckoning is bare.dead_reckoning
    assert with_sites.attach(sites[0] + 1, group.traverse.stops[sites[0] + 1]) is group.traverse.stops[sites[0] + 1]


def _three_groups_on_two_workers(failing):
    """Three groups waited for by side_by_side._wait on two "workers" (a pool of three threads:
    the wait must hold back): the futures it submitted and the most that ran at once. A failing
    group fails once the second group has started, and the others run until the wait is over:
    no timing decides the order."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from pancam_graph.solve.side_by_side import _wait

    running, most, lock = [0], [0], threading.Lock()
    second_started, waited = threading.Event(), threading.Event()

    def group(g: int) -> str:
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        if g == 1:
            second_started.set()
        if g == failing:
            second_started.wait(10.0)
            raise RuntimeError("group failed")
        waited.wait(0.05 if failing is None else 10.0)
        with lock:
            running[0] -= 1
        return "ok"

    futures = {}
    with ThreadPoolExecutor(3) as pool:
        def submit(g: int) -> None:
            futures[g] = pool.submit(group, g)

        _wait(futures, [0, 1, 2], submit, 2, [0, 0, 0, 0], 10, None)
        waited.set()
    return futures, most[0]


def test_groups_wait_for_a_free_worker_and_a_failure_stops_the_wait():
    """A group's job is submitted only when a worker is free (a queued job is held pickled in
    the run's process); the first group that fails ends the wait before the rest start."""
    futures, most = _three_groups_on_two_workers(None)
    assert len(futures) == 3 and most == 2 and all(f.result() == "ok" for f in futures.values())
    futures, most = _three_groups_on_two_workers(0)
    assert sorted(futures) == [0, 1] and most == 2
    with pytest.raises(RuntimeError, match="group failed"):
        futures[0].result()


def test_a_group_is_handed_its_inputs_in_a_file_with_large_arrays_mapped_once(short_trail):
    """Not through the pool's queue (whose feeder thread kept the last pickle); an array of a
    megabyte or more is written once for every group and mapped read-only by each worker."""
    import dataclasses

    from pancam_graph.solve.group import GroupJob
    from pancam_graph.solve.side_by_side import GroupInputs, Handover, read_once

    landmarks = np.arange(300_000, dtype=float).reshape(-1, 3)  # 2.4 MB
    truth = dataclasses.replace(short_trail.truth, landmarks=landmarks)
    job = GroupJob(short_trail.traverse, truth, short_trail.estimator, 0, SIDE_BY_SIDE, (), {})
    handover = Handover()
    try:
        first = handover.write("first", GroupInputs(job, None, [None], [None], 0.0))
        second = handover.write("second", GroupInputs(job, None, [None], [None], 0.0))
        assert len(list(handover.folder.glob("*.npy"))) == 1  # the same array, written once
        assert second.stat().st_size < landmarks.nbytes / 2
        got = read_once(first)
        assert not first.exists() and second.exists()
        np.testing.assert_array_equal(got.job.truth.landmarks, landmarks)
        assert not got.job.truth.landmarks.flags.writeable and not got.job.truth.landmarks.flags.owndata
        assert len(got.job.traverse.stops) == len(short_trail.traverse.stops)
    finally:
        handover.cleanup()
    assert not handover.folder.exists()


def test_a_groups_checkpoint_writer_travels_without_the_inputs(short_trail, tmp_path):
    """The writer a worker gets names its own traverse (refer_to); it used to carry the run's
    whole traverse, stereo and all, to every worker."""
    import pickle

    writer = CheckpointWriter(tmp_path, RunInputs(short_trail, SIDE_BY_SIDE), min_interval_s=0)
    part = writer.part(1)
    assert len(pickle.dumps(part)) < 2_000 < len(pickle.dumps(short_trail.traverse))
    assert writer.shared  # the run's own writer still names the inputs
