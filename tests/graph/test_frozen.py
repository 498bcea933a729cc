"""The rows of the variables that left the window: the same read back from memory, from files
and from a pickle."""

import pickle

import gtsam
import numpy as np

from pancam_graph.graph import frozen
from pancam_graph.graph.frozen import FrozenRows, row_of, value_of
from pancam_graph.graph.keys import E, L, S, X


def _filled(monkeypatch, count=9):
    monkeypatch.setattr(frozen, "CHUNK_ROWS", 3)
    rows, expected = FrozenRows(), {}
    for i in range(count):
        for key, width in ((X(i), 12), (L(100 + 2 * i), 3)):
            expected[key] = np.arange(width) + 1000.0 * i + key % 7
            rows.put(key, expected[key])
        rows.write_full()
    return rows, expected


def test_rows_read_back_from_memory_and_from_files_alike(monkeypatch):
    rows, expected = _filled(monkeypatch)
    assert rows.files == 4 and len(rows) == 18  # a file each four rows, two left in memory
    for key, row in expected.items():
        np.testing.assert_array_equal(rows.get(key), row)
    assert rows.get(X(9)) is None and L(101) not in rows
    assert not rows.get(X(0)).flags.writeable  # mapped read-only from its file
    assert dict((k, list(v)) for k, v in rows.items()) == {k: list(v) for k, v in expected.items()}

    keys = [X(8), X(3), X(42), X(0)]  # one in memory, two in files, one nowhere
    found, together = rows.rows(keys, 12)
    assert found.tolist() == [True, True, False, True]
    np.testing.assert_array_equal(together[[0, 1, 3]], [expected[k] for k in (X(8), X(3), X(0))])
    np.testing.assert_array_equal(together[2], np.zeros(12))


def test_a_row_put_again_before_its_file_replaces_it(monkeypatch):
    rows, _ = _filled(monkeypatch, count=1)  # two rows, fewer than a file's
    rows.put(X(0), np.full(12, 7.0))
    np.testing.assert_array_equal(rows.get(X(0)), np.full(12, 7.0))
    assert len(rows) == 2


def test_a_pickle_carries_the_rows_of_its_files(monkeypatch):
    rows, expected = _filled(monkeypatch)
    back = pickle.loads(pickle.dumps(rows))
    assert back.files == rows.files
    for key, row in expected.items():
        np.testing.assert_array_equal(back.get(key), row)


def test_every_kind_of_value_goes_to_a_row_and_back_exactly():
    values = gtsam.Values()
    pose = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 1.1), np.array([1.5, -2.25, 3.125]))
    values.insert(X(1), pose)
    values.insert(L(2), np.array([0.1, 0.2, 0.3]))
    values.insert(S(0), 0.0625)
    values.insert(E(3), np.array([1.0, 2.0, 3.0, 4.0]))
    assert row_of(values, X(1)).shape == (12,)
    np.testing.assert_array_equal(value_of(X(1), row_of(values, X(1))).matrix(), pose.matrix())
    np.testing.assert_array_equal(value_of(L(2), row_of(values, L(2))), [0.1, 0.2, 0.3])
    assert value_of(S(0), row_of(values, S(0))) == 0.0625
    np.testing.assert_array_equal(value_of(E(3), row_of(values, E(3))), [1.0, 2.0, 3.0, 4.0])
