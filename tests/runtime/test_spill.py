"""Numbers kept in files give back what went in, and leave no file behind."""

import pickle
import tempfile

import numpy as np
import pytest

from pancam_graph.runtime import spill
from pancam_graph.runtime.spill import Column


@pytest.mark.parametrize("typecode", ["q", "d"])
def test_a_column_reads_back_across_its_files(monkeypatch, typecode):
    monkeypatch.setattr(spill, "CHUNK", 5)
    rng = np.random.default_rng(3)
    values = rng.integers(-10**12, 10**12, 23) if typecode == "q" else rng.normal(size=23)
    column = Column(typecode, values[:7].tolist())
    for value in values[7:].tolist():
        column.append(value)
    assert len(column) == 23 and column._files and len(column._files) == 4  # 20 in files, 3 in memory
    np.testing.assert_array_equal(column.to_numpy(), values)
    assert list(column) == values.tolist()
    assert [column[i] for i in (0, 4, 5, 19, 20, 22, -1, -23)] == values[[0, 4, 5, 19, 20, 22, -1, -23]].tolist()
    assert type(column[0]) is type(values[:1].tolist()[0])  # a Python number, from a file as from memory
    with pytest.raises(IndexError):
        column[23]
    back = pickle.loads(pickle.dumps(column))  # a checkpoint, or a worker's results
    np.testing.assert_array_equal(back.to_numpy(), values)
    back.extend([1, 2, 3])
    assert len(back) == 26 and back.to_numpy()[-3:].tolist() == [1, 2, 3]


def test_mapped_files_are_gone_once_mapped(monkeypatch, tmp_path):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    values = np.arange(1000.0)
    copy = spill.mapped(values)
    np.testing.assert_array_equal(copy, values)
    assert not copy.flags.writeable
    assert list(tmp_path.iterdir()) == []  # unlinked: the mapping keeps the data
