"""A run killed with SIGKILL goes on from its last checkpoint (`run --resume`) and ends with
exactly the estimate of a run that was never stopped (issue 15). Real processes, as a user
would run them."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pancam_graph.formats.trajectories import read_tum
from pancam_graph.store.checkpoint import read_checkpoint, saved_stop

pytestmark = pytest.mark.slow

EXE = Path(sys.executable).parent / "pancam-graph"
CONFIGS = ("dead_reckoning", "vo", "vo_sites_hrc", "full")  # wheel slip, VO, site landmarks and HRC, GPS


# the smoothers' update logs in files of 2 updates, so the checkpoint refers to some
ENV = {**os.environ, "PANCAM_GRAPH_LOG_CHUNK_UPDATES": "2"}


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(EXE), *args], cwd=cwd, capture_output=True, text=True, timeout=300, env=ENV)


def _start_until_first_checkpoint(tmp_path: Path, past_stop: int = 0, *options: str,
                                 source: str = "short_trail") -> subprocess.Popen:
    """A run of `source` (short_trail) saving at every checkpoint, once it has saved a state past
    `past_stop`."""
    run = subprocess.Popen([str(EXE), "run", source, "--out", "res", "--quiet", "--checkpoint-every", "0",
                            *options],
                           cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    state = tmp_path / "res.partial" / "checkpoint" / "state.pkl"
    deadline = time.time() + 120
    while (saved_stop(state) or -1) <= past_stop and run.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    return run


def _killed_past(tmp_path: Path, past_stop: int, *options: str, source: str = "short_trail") -> None:
    """That run (_start_until_first_checkpoint) killed with SIGKILL, its staging folder left behind."""
    killed = _start_until_first_checkpoint(tmp_path, past_stop, *options, source=source)
    assert killed.poll() is None, "the run ended before it could be killed"
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()


def test_a_killed_run_resumes_to_the_same_estimate(tmp_path):
    whole = _run("run", "short_trail", "--out", "whole", "--quiet", "--no-plots", cwd=tmp_path)
    assert whole.returncode == 0, whole.stderr

    _killed_past(tmp_path, 10)
    _, [saved] = read_checkpoint(tmp_path / "res.partial")  # short_trail runs in one process
    stops = len(saved.localizers["vo"].traverse.stops)
    assert 0 < saved.next_stop < stops  # killed midway
    log = saved.localizers["vo"].smoother.log
    assert log.files >= 1 and (tmp_path / "res.partial" / "checkpoint" / "log" / "vo" / "chunk-00000.pkl").is_file()

    resumed = _run("run", "--resume", "res.partial", "--quiet", "--no-plots", cwd=tmp_path)  # trajectories compared
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming short_trail at stop {saved.next_stop} of {stops}" in resumed.stderr
    assert not (tmp_path / "res.partial").exists() and not (tmp_path / "res" / "checkpoint").exists()
    for name in CONFIGS:
        a, b = (read_tum(tmp_path / folder / f"trajectory_{name}.tum") for folder in ("whole", "res"))
        assert len(b.times_s) == stops
        np.testing.assert_array_equal(a.world_T_body, b.world_T_body)


def test_a_killed_run_with_the_estimated_calibration_resumes_to_the_same_estimate(tmp_path):
    """The stereo_calibration kind's views are Python factors, made again from their recipes
    (short_trail as bundled: the realistic profile, which estimates the calibration)."""
    whole = _run("run", "short_trail", "--configs", "vo_sites", "--out", "whole", "--quiet", "--no-plots",
                 cwd=tmp_path)
    assert whole.returncode == 0, whole.stderr
    _killed_past(tmp_path, 60, "--configs", "vo_sites", source="short_trail")
    _, [saved] = read_checkpoint(tmp_path / "res.partial")
    assert "stereo_calibration" in saved.localizers["vo_sites"].kinds
    sites_before = sum(stop.is_site for stop in saved.localizers["vo_sites"].traverse.stops[:saved.next_stop])
    assert sites_before >= 2  # calibrated views in the checkpoint's log
    resumed = _run("run", "--resume", "res.partial", "--quiet", "--no-plots", cwd=tmp_path)  # trajectories compared
    assert resumed.returncode == 0, resumed.stderr
    a, b = (read_tum(tmp_path / folder / "trajectory_vo_sites.tum") for folder in ("whole", "res"))
    np.testing.assert_array_equal(a.world_T_body, b.world_T_body)


def test_a_live_runs_folder_cannot_be_resumed(tmp_path):
    live = _start_until_first_checkpoint(tmp_path, 0, "--configs", "vo")
    second = _run("run", "--resume", "res.partial", "--quiet", cwd=tmp_path)
    assert live.wait(timeout=300) == 0
    assert second.returncode == 2 and "in use by run" in second.stderr, second.stderr
    assert (tmp_path / "res" / "metrics.json").is_file()  # the live run finished undisturbed


def test_a_full_disk_is_one_line_exit_1_and_the_partial_folder_stays(tmp_path):
    """Files over 400 kB cannot be written (RLIMIT_FSIZE: the write fails as on a full disk)."""
    import resource

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    result = subprocess.run([str(EXE), "run", "short_trail", "--out", "res", "--quiet"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300, preexec_fn=small_files)
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        "error: res.partial/checkpoint/inputs.pkl: cannot write the checkpoint: File too large"]
    assert (tmp_path / "res.partial").is_dir() and not (tmp_path / "res").exists()


@pytest.mark.parametrize("args,says", [
    (["run", "short_trail", "--out", "res", "--quiet", "--one-process"],
     "res.partial/.lock: cannot write the run's lock file"),
    (["run", "short_trail", "--out", "res", "--quiet"], "No usable temporary directory"),  # the process server's
    (["simulate", "short_trail", "--out", "res"], "res: cannot write the observation folder"),
    (["eval", "TRAJECTORY", "TRAJECTORY", "--out", "res"], "res: cannot write the evaluation"),
])
def test_a_disk_with_no_space_is_one_line_naming_the_path_and_leaves_nothing(tmp_path_factory, args, says):
    """No file can grow past 0 bytes (RLIMIT_FSIZE 0: every write fails as on a full disk)."""
    import resource

    trajectory = tmp_path_factory.mktemp("input") / "line.tum"
    trajectory.write_text("".join(f"{t} {t} 0 0 0 0 0 1\n" for t in range(20)))
    work = tmp_path_factory.mktemp("full")

    def no_space():
        resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0))

    result = subprocess.run([str(EXE), *(str(trajectory) if a == "TRAJECTORY" else a for a in args)], cwd=work,
                            capture_output=True, text=True, timeout=120, preexec_fn=no_space)
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0], result.stderr
    assert list(work.iterdir()) == []  # no staging folder, no half-written output


def test_ctrl_c_says_where_the_work_is_and_the_run_resumes_from_there(tmp_path):
    """SIGINT used to stop a run silently (typer turns it into a bare exit 130)."""
    interrupted = _start_until_first_checkpoint(tmp_path, 0, "--configs", "vo,full")
    interrupted.send_signal(signal.SIGINT)
    _, err = interrupted.communicate(timeout=60)
    assert interrupted.returncode == 130
    _, [saved] = read_checkpoint(tmp_path / "res.partial")
    assert err == ("interrupted: what was done is in res.partial; `pancam-graph run --resume res.partial` goes on "
                   f"from stop {saved.next_stop}\n")
    resumed = _run("run", "--resume", "res.partial", "--quiet", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert (tmp_path / "res" / "trajectory_full.tum").is_file()
