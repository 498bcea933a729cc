"""A traverse's motions as columns: every motion read back as it was put, across blocks, from a
pickle and from read-only (mapped) columns."""

import pickle

import gtsam
import numpy as np
import pytest

from pancam_graph.frontend.motion import Motion, Motions
from pancam_graph.records import DeadReckoning


def _motions(count=11):
    rng = np.random.default_rng(3)
    out = [None]
    for k in range(1, count):
        pose = gtsam.Pose3(gtsam.Rot3.Ypr(*rng.normal(0, 0.1, 3)), rng.normal(0, 1, 3))
        a = rng.normal(size=(6, 6))
        covariance = a @ a.T
        if k % 3 == 0:
            odometry = DeadReckoning(pose.matrix(), covariance)
            out.append(Motion(pose, covariance, "dead_reckoning", 4, "too few inliers", odometry=odometry))
        elif k % 3 == 1:
            out.append(Motion(pose, covariance, "vo", 100 + k))
        else:
            out.append(Motion(pose, np.diag(np.arange(1.0, 7.0)), "constant_velocity", 0, "no features"))
    return out


def _assert_same(got, expected):
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        if b is None:
            assert a is None
            continue
        np.testing.assert_array_equal(a.prev_T_curr.matrix(), b.prev_T_curr.matrix())
        np.testing.assert_array_equal(a.covariance, b.covariance)
        assert (a.source, a.vo_inliers, a.vo_failure) == (b.source, b.vo_inliers, b.vo_failure)
        assert a.odometry is b.odometry  # the stop's own record, not a copy


def test_motions_read_back_as_they_were_put_across_blocks(monkeypatch):
    monkeypatch.setattr(Motions, "BLOCK", 4)
    expected = _motions()
    motions = Motions(expected)
    _assert_same(list(motions), expected)
    _assert_same(motions[2:7], expected[2:7])
    _assert_same([motions[-1]], [expected[-1]])
    assert motions.vo_inliers().tolist() == [-1] + [m.vo_inliers for m in expected[1:]]
    with pytest.raises(IndexError):
        motions[11]


def test_a_pickle_of_motions_reads_back_and_goes_on(monkeypatch):
    monkeypatch.setattr(Motions, "BLOCK", 4)
    expected = _motions()
    # pickled with the stops' records, as a worker's inputs are: the same records come back
    back, expected = pickle.loads(pickle.dumps((Motions(expected[:6]), expected)))
    back.extend(expected[6:])  # into the last block read back, then new ones
    _assert_same(list(back), expected)


def test_motions_on_read_only_columns_copy_a_block_before_writing_it(monkeypatch):
    monkeypatch.setattr(Motions, "BLOCK", 4)
    expected = _motions(count=8)  # two full blocks: the last is read back as a view
    state = Motions(expected).__getstate__()
    for name in ("numbers", "codes"):
        state[name].flags.writeable = False  # as a worker maps them
    mapped = Motions.__new__(Motions)
    mapped.__setstate__(state)
    extra = _motions(count=12)[8:]
    mapped.extend(extra)
    _assert_same(list(mapped), expected + extra)
