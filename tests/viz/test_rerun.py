"""The rerun recording of a run, read back with rerun's own reader."""

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from rrd import Recording, array
from scipy.stats import chi2

from pancam_graph.geometry.geodesy import LocalFrame
from pancam_graph.solve.pipeline import RunOptions, run_scenario
from pancam_graph.viz.rerun_live import RerunRecorder
from pancam_graph.viz.rerun_sink import RerunTarget, open_recording

TESTS = Path(__file__).parents[1]
REFRESH_TEST = 40


@pytest.fixture(scope="module")
def recorded(short_scenario, tmp_path_factory):
    path = tmp_path_factory.mktemp("rerun") / "run.rrd"
    recording = open_recording(RerunTarget("save", path=path), "test")
    recorder = RerunRecorder(recording, refresh_every=REFRESH_TEST)  # short_trail: 140 stops
    result = run_scenario(short_scenario, RunOptions(seed=0), listener=recorder)
    recording.close()
    return result, recorder, Recording(path)


@pytest.mark.slow
def test_recording_has_the_documented_entities(recorded):
    result, _, rec = recorded
    expected = {"/world", "/world/terrain", "/world/truth", "/world/gps", "/world/sites", "/world/sites/panoramas",
                "/world/rover", "/world/rover/left_cam", "/world/rover/left_cam/features", "/map/gps", "/map/truth",
                "/map/rover", "/events", "/plots/vo_inliers"}
    for config in result.configurations:
        expected |= {f"/world/estimate/{config}/trajectory", f"/world/estimate/{config}/covariance",
                     f"/map/estimate/{config}", f"/plots/error_m/{config}", f"/plots/isam2_update_ms/{config}",
                     f"/plots/relinearized/{config}"}
    expected |= {"/world/estimate/vo_sites/landmarks", "/world/estimate/vo_sites/ties", "/plots/gps_outliers/full"}
    assert expected <= rec.entity_paths
    assert "/world/estimate/vo/landmarks" not in rec.entity_paths  # VO alone has no landmarks


def test_trajectory_points_at_a_stop(recorded):
    result, recorder, rec = recorded
    primary = recorder.primary
    assert primary == "full"
    # The primary configuration's line follows the rover at every stop: the whole trajectory as
    # at the last refresh, and its tail since then, ending on the stop's pose...
    for k in (5, 37, 101):
        last_refresh = max((r for r in range(k + 1) if (r + 1) % recorder.refresh_every == 0), default=None)
        tail = rec.at(f"/world/estimate/{primary}/trajectory/tail", k, "LineStrips3D:strips")
        assert len(tail) == 1 and len(tail[0]) == k + 1 - (last_refresh or 0)
        if last_refresh is not None:
            whole = rec.at(f"/world/estimate/{primary}/trajectory", last_refresh, "LineStrips3D:strips")[0]
            assert len(whole) == last_refresh + 1
            np.testing.assert_allclose(array(tail[0])[0], array(whole)[-1], atol=1e-5)  # one line
    # ...the others at refresh stops (every `refresh_every`, and the last) only.
    vo_stops = rec.stops("/world/estimate/vo/trajectory")
    n = len(result.traverse.stops)
    refreshes = [k for k in range(n) if (k + 1) % recorder.refresh_every == 0]
    assert n > 2 * recorder.refresh_every
    refreshed = refreshes[1]
    assert set(vo_stops) == {*refreshes, n - 1}  # no site forces one: the browser keeps up
    assert len(rec.at("/world/estimate/vo/trajectory", refreshed, "LineStrips3D:strips")[0]) == refreshed + 1
    # At the end the final estimate replaces the live one.
    final = array(rec.latest(f"/world/estimate/{primary}/trajectory", "LineStrips3D:strips")[0])
    np.testing.assert_allclose(final, result.configurations[primary].world_T_body[:, :3, 3], atol=1e-4)


def test_covariance_ellipsoids_are_the_95_percent_marginals(recorded):
    result, _, rec = recorded
    c = result.configurations["vo"]
    # Final ellipsoids: at every site and the last stop, from the final marginals.
    rows = [i for i, s in enumerate(result.traverse.stops) if s.is_site] + [len(result.traverse.stops) - 1]
    half = array(rec.latest("/world/estimate/vo/covariance", "Ellipsoids3D:half_sizes"))
    centres = array(rec.latest("/world/estimate/vo/covariance", "Ellipsoids3D:centers"))
    assert len(half) == len(rows)
    expected = np.sqrt(chi2.ppf(0.95, 3) * np.linalg.eigvalsh(c.position_covariance[rows]))
    np.testing.assert_allclose(np.sort(half, axis=1), expected, rtol=1e-5)
    np.testing.assert_allclose(centres, c.world_T_body[rows, :3, 3], atol=1e-4)
    # Live: VO alone grows its uncertainty with distance; the ellipsoid sits on the current pose.
    first, third = REFRESH_TEST - 1, 3 * REFRESH_TEST - 1  # refreshes
    early = array(rec.at("/world/estimate/vo/covariance", first, "Ellipsoids3D:half_sizes"))
    late = array(rec.at("/world/estimate/vo/covariance", third, "Ellipsoids3D:half_sizes"))
    assert late.max() > 3 * early.max()
    strip = array(rec.at("/world/estimate/vo/trajectory", third, "LineStrips3D:strips")[0])
    np.testing.assert_allclose(array(rec.at("/world/estimate/vo/covariance", third, "Ellipsoids3D:centers"))[0],
                               strip[-1], atol=1e-4)


def test_geo_points_are_the_gps_fixes_and_the_map_line_is_the_estimate(recorded):
    result, _, rec = recorded
    fixes = result.traverse.gps_fixes
    geo = array(rec.latest("/map/gps", "GeoPoints:positions"))
    np.testing.assert_allclose(geo, [[f.lat_deg, f.lon_deg] for f in fixes], atol=1e-12)
    line = array(rec.latest("/map/estimate/full", "GeoLineStrings:line_strings")[0])
    o = result.scenario.origin
    final = result.configurations["full"].world_T_body[:, :3, 3]
    h = LocalFrame(o.lat_deg, o.lon_deg, o.h_m).to_geodetic(final)[:, 2]  # the line carries no height
    enu = LocalFrame(o.lat_deg, o.lon_deg, o.h_m).to_enu(line[:, 0], line[:, 1], h)
    np.testing.assert_allclose(enu, final, atol=1e-3)


def test_series_hold_one_value_per_stop(recorded):
    result, _, rec = recorded
    n = len(result.traverse.stops)
    update = [row["Scalars:scalars"][0] for _, row in rec.temporal["/plots/isam2_update_ms/vo_sites"]]
    np.testing.assert_allclose(update, result.configurations["vo_sites"].update_ms, rtol=1e-9)
    errors = [row["Scalars:scalars"][0] for _, row in rec.temporal["/plots/error_m/vo"]]
    # at stop 0 the live estimate is the surveyed start, off the truth by its survey error
    survey_error = np.linalg.norm(result.traverse.start_world_T_body[:3, 3] - result.truth.positions[0])
    assert len(errors) == n and errors[0] == pytest.approx(survey_error, abs=1e-6) and max(errors) < 1.0


KILLED_RUN = textwrap.dedent("""
    import os, signal, sys
    from pancam_graph.config import load_scenario, resolve_scenario
    from pancam_graph.solve.pipeline import RunOptions, run_scenario
    from pancam_graph.viz.rerun_live import RerunRecorder
    from pancam_graph.viz.rerun_sink import RerunTarget, open_recording

    class KilledAfterSecondSend(RerunRecorder):
        def step(self, stop, motion, steps):
            super().step(stop, motion, steps)  # sends at every refresh_every-th stop
            if stop.index == 2 * self.refresh_every - 1:
                print(stop.index, flush=True)
            if stop.index == 2 * self.refresh_every + 2:
                os.kill(os.getpid(), signal.SIGKILL)  # no flush, no footer: like a power cut

    from pathlib import Path
    recording = open_recording(RerunTarget("save", path=Path(sys.argv[1])), "killed")
    run_scenario(load_scenario(resolve_scenario("short_trail")), RunOptions(seed=0),
        listener=KilledAfterSecondSend(recording, refresh_every=40))
""")


@pytest.mark.slow
def test_killed_run_leaves_a_recording_readable_up_to_the_last_send(tmp_path):
    path = tmp_path / "killed.rrd"
    proc = subprocess.run([sys.executable, "-c", KILLED_RUN, str(path)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(TESTS.parent)})
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    checkpoint = int(proc.stdout.split()[0])
    assert checkpoint == 2 * 40 - 1
    rec = Recording(path)
    stops = rec.stops("/world/estimate/full/trajectory/tail")
    assert checkpoint <= max(stops) <= checkpoint + 3  # everything to the checkpoint, nothing after the kill
    assert stops[: checkpoint + 1] == list(range(checkpoint + 1))
    strip = rec.at("/world/estimate/full/trajectory", checkpoint, "LineStrips3D:strips")[0]
    assert len(strip) == checkpoint + 1  # refreshed there
    # the series sent then are there too
    assert len(rec.temporal["/plots/isam2_update_ms/full"]) >= checkpoint + 1


def test_core_never_imports_rerun():
    code = ("import sys; import pancam_graph.solve.pipeline, pancam_graph.solve.localizer, "
            "pancam_graph.store.results_folder; "
            "sys.exit(1 if any(m == 'rerun' or m.startswith('rerun.') for m in sys.modules) else 0)")
    env = {**os.environ, "PYTHONPATH": str(TESTS.parent)}
    assert subprocess.run([sys.executable, "-c", code], env=env).returncode == 0


def _listening(port: int) -> set[str]:
    import psutil

    return {c.laddr.ip for c in psutil.net_connections("tcp") if c.status == "LISTEN" and c.laddr.port == port}


@pytest.mark.slow
def test_serve_prints_a_web_viewer_url_that_opens_the_recording_before_the_run_is_done(tmp_path):
    """`--rerun serve`: the web viewer is up, on 127.0.0.1 and a URL that names the recording
    (?url=...), before the run has written its results; with --serve-for it stops after that."""
    import re
    import urllib.request

    from served import serve_run

    run, url = serve_run("short_trail", "--out", str(tmp_path / "res"), "--serve-for", "1")
    try:
        finished_before = (tmp_path / "res" / "metrics.json").exists()
        found = re.fullmatch(r"http://127\.0\.0\.1:(\d+)/\?url=rerun%2Bhttp%3A%2F%2F127\.0\.0\.1%3A(\d+)%2Fproxy", url)
        assert found, url
        assert not finished_before  # announced when the recording opened, not after the run
        web, grpc = int(found[1]), int(found[2])
        assert _listening(web) == {"127.0.0.1"} and _listening(grpc) == {"127.0.0.1"}  # not every interface
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200
        assert run.wait(timeout=120) == 0  # served 1 s after the run, then done
        assert "stays at" in run.stderr.read()
        assert (tmp_path / "res" / "metrics.json").exists()
        assert not _listening(web) and not _listening(grpc)  # the server went with the run
    finally:
        run.kill()
        run.wait()


FULL_DISK = textwrap.dedent("""
    import os, resource, sys
    from pathlib import Path
    import numpy as np
    import rerun as rr
    from pancam_graph.viz import rerun_sink
    from pancam_graph.viz.rerun_sink import RerunTarget, open_recording

    rerun_sink.FLUSH_TIMEOUT_S = 2.0  # the run's 15 s, shortened for the test
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))  # a write past 100 kB fails (EFBIG)
    recording = open_recording(RerunTarget("save", path=Path(sys.argv[1])), "full disk")
    recording.stream.log("points", rr.Points3D(np.random.default_rng(0).random((50_000, 3))))
    print(recording.flush(), recording.failure, flush=True)
    recording.close()
    os._exit(0)  # as the CLI does: rerun's exit handler would wait for the stream for ever
""")


@pytest.mark.slow
def test_a_recording_that_cannot_be_written_is_given_up_not_waited_on(tmp_path):
    """rerun's file sink waited for ever on a full disk (flush, disconnect and exit): the
    recording's flush gives up within its time limit and says why."""
    path = tmp_path / "full.rrd"
    proc = subprocess.run([sys.executable, "-c", FULL_DISK, str(path)], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(TESTS.parent)})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"False rerun: the recording stopped: cannot write {path} (a full disk?)")


@pytest.mark.slow
def test_a_recording_file_that_cannot_be_written_is_a_warning_and_the_run_finishes(tmp_path):
    (tmp_path / "full.rrd").symlink_to("/dev/full")  # every write: no space left on device
    result = subprocess.run([str(Path(sys.executable).parent / "pancam-graph"), "run", "short_trail", "--out", "res",
                             "--quiet", "--configs", "vo", "--rerun", "save:full.rrd"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert warnings == ["warning: rerun: cannot open the recording (full.rrd): Failed to encode LogMsg: Failed to "
                        "write: No space left on device (os error 28); running without it"], result.stderr
    assert "Traceback" not in result.stderr and (tmp_path / "res" / "metrics.json").is_file()
