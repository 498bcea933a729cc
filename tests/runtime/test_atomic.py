"""Files written whole or not at all (runtime/atomic.py): an interruption mid-write (Ctrl-C)
leaves the old file as it was and no temporary beside it (a resumed run found state-1.pkl.tmp
left in its checkpoint folder)."""

import pytest

from pancam_graph.runtime.atomic import write_atomically


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_a_write_stopped_midway_leaves_the_old_file_and_no_temporary(tmp_path, stop):
    path = tmp_path / "state-1.pkl"
    write_atomically(path, lambda f: f.write(b"old"))

    def half_then_stopped(f):
        f.write(b"half of the new")
        raise stop()

    with pytest.raises(stop):
        write_atomically(path, half_then_stopped)
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state-1.pkl"]
