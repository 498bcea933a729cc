import gtsam
import numpy as np
import pytest

from pancam_graph.errors import ResultsError
from pancam_graph.store.results_folder import read_tum, results_folder, write_tum


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.stack([gtsam.Pose3(gtsam.Rot3.Ypr(*rng.uniform(-3, 3, 3)), rng.uniform(-500, 500, 3)).matrix()
                      for _ in range(20)])
    times = np.arange(20) * 37.5
    write_tum(tmp_path / "t.tum", times, poses)
    t2, p2 = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(t2, times, atol=1e-3)
    np.testing.assert_allclose(p2, poses, atol=1e-6)


def test_failed_run_keeps_partial_folder_and_never_overwrites(tmp_path):
    out = tmp_path / "res"
    with pytest.raises(RuntimeError), results_folder(out) as staging:
        (staging / "metrics.json").write_text("{}")
        raise RuntimeError("fault midway")
    assert not out.exists()
    assert (tmp_path / "res.partial" / "metrics.json").exists()  # nothing computed is lost
    with results_folder(out) as staging:
        (staging / "a.txt").write_text("done")
    assert (out / "a.txt").read_text() == "done"
    # the failed run's folder was set aside, not deleted
    assert (tmp_path / "res.partial.1" / "metrics.json").exists()
    with pytest.raises(ResultsError, match="not empty"), results_folder(out):
        pass
