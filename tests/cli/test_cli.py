import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader
from rrd import Recording, array
from typer.testing import CliRunner

from pancam_graph.cli import app
from pancam_graph.store.results_folder import read_tum

runner = CliRunner()

GOOD = """
name = "tiny"
[origin]
lat_deg = 39.7
lon_deg = -105.1
[path]
waypoints = [[0.0, 0.0, 0.0], [30.0, 0.0, 0.0]]
"""


@pytest.mark.parametrize(
    "text,field",
    [
        (GOOD.replace("[path]", "[path]\nspeeed_mps = 1.0"), "path.speeed_mps"),
        (GOOD.replace('name = "tiny"', 'name = "tiny"\nseed = "zero"'), "seed"),
        (GOOD.replace("lat_deg = 39.7", "lat_deg = 95.0"), "origin.lat_deg"),
        (GOOD.replace("[path]", "[path]\nstop_spacing_m = [2.0, 1.0]"), "path.stop_spacing_m"),
    ],
)
def test_bad_scenario_is_rejected_naming_file_and_field(tmp_path, text, field):
    bad = tmp_path / "bad_scenario.toml"
    bad.write_text(text)
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(bad), "--out", str(out)])
    assert result.exit_code == 2
    assert "bad_scenario.toml" in result.output
    assert f"'{field}'" in result.output
    assert "Traceback" not in result.output
    assert not out.exists() and not (tmp_path / "out.partial").exists()


def test_missing_scenario_file(tmp_path):
    result = runner.invoke(app, ["run", str(tmp_path / "nope.toml")])
    assert result.exit_code == 2 and "nope.toml" in result.output


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """One CLI run of the short scenario, seed 3, recorded with `--rerun save`."""
    out = tmp_path_factory.mktemp("cli") / "res"
    result = runner.invoke(app, ["run", "short_trail", "--out", str(out), "--quiet", "--seed", "3",
                                 "--rerun", "save"])
    assert result.exit_code == 0, result.output
    return out


@pytest.mark.slow
def test_steps_csv_carries_each_stops_estimate_error_and_sigma(results):
    """steps.csv's estimate columns against the run's own trajectory, truth and covariance files,
    read here with the csv module and numpy; the last stop's error is metrics.json's closure."""
    import csv

    rows = [r for r in csv.DictReader((results / "steps.csv").open()) if r["config"] == "vo_sites"]
    truth = np.loadtxt(results / "truth.tum")[:, 1:4]
    estimate = np.loadtxt(results / "trajectory_vo_sites.tum")[:, 1:4]
    covariance = np.loadtxt(results / "covariance_vo_sites.csv", delimiter=",", skiprows=1)
    column = {name: np.array([float(r[name]) for r in rows]) for name in
              ("distance_m", "east_m", "north_m", "up_m", "error_2d_m", "sigma_2d_m", "sigma_up_m")}
    np.testing.assert_allclose(np.column_stack([column["east_m"], column["north_m"], column["up_m"]]), estimate,
                               atol=1e-3)
    np.testing.assert_allclose(column["error_2d_m"], np.hypot(*(estimate - truth)[:, :2].T), atol=1e-3)
    np.testing.assert_allclose(column["distance_m"][-1], np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1)),
                               rtol=1e-4)
    np.testing.assert_allclose(column["sigma_2d_m"], np.sqrt(covariance[:, 1] + covariance[:, 4]), atol=6e-5)
    np.testing.assert_allclose(column["sigma_up_m"], np.sqrt(covariance[:, 6]), atol=6e-5)
    closure = json.loads((results / "metrics.json").read_text())["configs"]["vo_sites"]["closure_error_2d_m"]
    assert column["error_2d_m"][-1] == pytest.approx(closure, abs=1e-3)


@pytest.mark.slow
def test_run_writes_a_complete_results_folder(results, tmp_path):
    out = results
    names = {p.name for p in out.iterdir()}
    assert {"scenario.toml", "metrics.json", "truth.tum", "gps_fixes.csv", "motions.csv", "steps.csv",
            "panoramas.csv", "truth_landmarks.npy", "recording.rrd", "report.md", "trajectories.png",
            "error_vs_distance.png", "distance_relation.png", "elevation_profile.png"} <= names
    for config in ("vo", "vo_sites", "vo_sites_hrc", "full"):
        assert {f"trajectory_{config}.tum", f"covariance_{config}.csv", f"landmarks_{config}.csv"} <= names
    metrics = json.loads((out / "metrics.json").read_text())
    for config in metrics["configs"].values():
        for key in ("average_error_m", "closure_error_m", "relative_closure_pct", "ate_rmse_m",
                    "reference_length_m", "length_ratio", "bridged_stops"):
            assert isinstance(config[key], (int, float))
    assert {"median", "p99"} <= metrics["timing"]["isam2_update_ms"].keys()
    assert metrics["timing"]["wall_s"] > 0
    # the resolved scenario re-runs
    again = runner.invoke(app, ["run", str(out / "scenario.toml"), "--out", str(tmp_path / "again"),
                                "--quiet", "--seed", "3", "--configs", "vo,vo_sites"])
    assert again.exit_code == 0, again.output
    rerun = json.loads((tmp_path / "again" / "metrics.json").read_text())["configs"]["vo"]
    original = metrics["configs"]["vo"]
    for timing in (rerun, original):
        timing.pop("isam2_update_ms")
    assert rerun == original
    # a results folder is never overwritten
    clash = runner.invoke(app, ["run", "short_trail", "--out", str(out), "--quiet"])
    assert clash.exit_code == 2 and "not empty" in clash.output


def test_report_tabulates_the_metrics_and_shows_the_figures(results):
    report = (results / "report.md").read_text()
    metrics = json.loads((results / "metrics.json").read_text())
    for name, m in metrics["configs"].items():
        row = next(line for line in report.splitlines() if line.startswith(f"| {name} |"))
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == "+".join(m["kinds"])
        assert float(cells[4]) == pytest.approx(m["relative_closure_pct"], abs=5e-5)
        assert float(cells[2]) == pytest.approx(m["average_error_m"], abs=5e-4)
    for png in ("trajectories.png", "error_vs_distance.png", "distance_relation.png", "elevation_profile.png"):
        assert f"]({png})" in report
        assert (results / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_saved_recording_is_complete_and_has_its_footer(results):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rerun warns when a file has no footer (an unfinished write)
        RrdReader(str(results / "recording.rrd"))
    rec = Recording(results / "recording.rrd")
    _, truth = read_tum(results / "truth.tum")
    assert rec.stops("/world/estimate/full/trajectory/tail") == list(range(len(truth)))  # every stop


def test_view_replays_a_results_folder_with_the_same_entities(results, tmp_path):
    replay = tmp_path / "replay.rrd"
    result = runner.invoke(app, ["view", str(results), "--rerun", f"save:{replay}"])
    assert result.exit_code == 0, result.output
    live, again = Recording(results / "recording.rrd"), Recording(replay)
    # the same scene, less what a results folder does not hold (camera features, the event log)
    assert live.entity_paths - again.entity_paths <= {"/world/rover/left_cam/features", "/events", "/map/rover",
                                                      "/__properties"}
    times, final = read_tum(results / "trajectory_vo_sites.tum")
    for k in (0, 17, len(times) - 1):
        strip = array(again.at("/world/estimate/vo_sites/trajectory", k, "LineStrips3D:strips")[0])
        np.testing.assert_allclose(strip, final[: k + 1, :3, 3], atol=1e-4)
    assert len(again.temporal["/plots/error_m/full"]) == len(times)


def test_view_names_what_is_wrong_with_a_results_folder(results, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["view", str(empty), "--rerun", f"save:{tmp_path / 'x.rrd'}"])
    assert result.exit_code == 2 and "run.toml" in result.output and "Traceback" not in result.output
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in results.iterdir():
        (broken / f.name).write_bytes(f.read_bytes())
    lines = (broken / "steps.csv").read_text().splitlines()
    (broken / "steps.csv").write_text("\n".join([lines[0].replace("update_ms", "update")] + lines[1:]))
    result = runner.invoke(app, ["view", str(broken), "--rerun", f"save:{tmp_path / 'y.rrd'}"])
    assert result.exit_code == 2 and "steps.csv" in result.output and "update_ms" in result.output
    assert not (tmp_path / "y.rrd").exists() or (tmp_path / "y.rrd").stat().st_size < 10_000


def test_bad_rerun_option_is_a_usage_error_and_writes_nothing(tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", "short_trail", "--out", str(out), "--rerun", "sav"])
    assert result.exit_code == 2 and "expected spawn, save" in result.output
    assert not out.exists() and not (tmp_path / "out.partial").exists()


@pytest.mark.slow
def test_bench_prints_json(tmp_path):
    result = runner.invoke(app, ["bench", "short_trail", "--plot", str(tmp_path / "cost.png")])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["isam2_update_ms"]["median"] > 0
    assert report["isam2_update_ms"]["p99"] >= report["isam2_update_ms"]["median"]
    memory = report["peak_memory_mb"]
    assert report["wall_s"] > 0 and memory["rss"]["sum"] >= memory["rss"]["this process"] > 0
    assert memory["pss"]["sum"] >= memory["pss"]["this process"] > 0 and memory["at_once"] > 0
    # cost along the path, per 1 km window (short_trail: one window holding every stop's update)
    assert [w["updates"] for w in report["isam2_update_ms_per_km"]["vo"]] == [report["stops"][0]]
    (along,) = report["rss_mb_along_path"].values()  # short_trail runs in one process, one group
    assert len(along) >= 2 and along[-1]["at_m"] > along[0]["at_m"]
    assert all(100 < m["rss_mb"] < 4000 for m in along)
    assert (tmp_path / "cost.png").stat().st_size > 10_000


def test_scenarios_lists_bundled_files():
    result = runner.invoke(app, ["scenarios"])
    assert result.exit_code == 0
    for name in ("denver_trail", "straight_500m", "gps_multipath", "short_trail", "long_traverse", "sparse_sites"):
        assert name in result.output
    assert "(invalid" not in result.output


@pytest.mark.slow
def test_the_reproduce_line_reproduces_the_run(tmp_path, monkeypatch):
    out = tmp_path / "first"
    first = runner.invoke(app, ["run", "short_trail", "--seed", "5", "--configs", "vo,vo+gps", "--batch",
                                "--quiet", "--out", str(out)])
    assert first.exit_code == 0, first.output
    line = next(x for x in (out / "report.md").read_text().splitlines() if x.startswith("- reproduce"))
    command = line.split("`")[1].split()
    assert command[:2] == ["pancam-graph", "run"] and "--batch" in command and "vo,vo+gps" in command
    monkeypatch.chdir(out)  # a scenario run reproduces from its folder's scenario.toml
    again = runner.invoke(app, [*command[1:], "--quiet", "--out", str(tmp_path / "again")])
    assert again.exit_code == 0, again.output

    def configs(folder):
        document = json.loads((folder / "metrics.json").read_text())
        for c in document["configs"].values():
            c.pop("isam2_update_ms")
        return document["configs"], document["seed"]

    assert configs(tmp_path / "again") == configs(out)
    run_toml = (out / "run.toml").read_text()
    assert 'batch = true' in run_toml and '"vo+gps" = [' in run_toml and "gtsam" in run_toml


def test_eval_reads_the_tools_own_wgs84_trajectory_and_gps_log(results, tmp_path):
    """A results folder's `trajectory_vo_wgs84.csv` (h_ellipsoidal_m) against its `gps_fixes.csv`
    gives what the TUM file of the same trajectory gives (issue 15: eval rejected it)."""
    closure = {}
    for estimate in ("trajectory_vo_wgs84.csv", "trajectory_vo.tum"):
        out = tmp_path / estimate
        # the body's origin on both sides: the CSV has no attitude to carry the antenna's lever arm
        result = runner.invoke(app, ["eval", str(results / estimate), str(results / "gps_fixes.csv"),
                                     "--lever-arm", "0,0,0", "--out", str(out)])
        assert result.exit_code == 0, result.output
        (metrics,) = json.loads((out / "metrics.json").read_text())["configs"].values()
        closure[estimate] = metrics["closure_error_m"]
    assert closure["trajectory_vo_wgs84.csv"] == pytest.approx(closure["trajectory_vo.tum"], abs=1e-3)
    assert closure["trajectory_vo.tum"] > 0.1  # the GPS log is noisy: a real difference, not zero


def test_eval_against_the_runs_own_fixes_gives_its_vs_gps(results, tmp_path):
    """A trajectory with attitudes against a GPS log is compared at the antenna (the lever arm
    saved in local_frame.json): the figures the run itself reports as vs_gps."""
    run = json.loads((results / "metrics.json").read_text())["configs"]
    for name in ("vo", "full"):
        out = tmp_path / name
        result = runner.invoke(app, ["eval", str(results / f"trajectory_{name}.tum"), str(results / "gps_fixes.csv"),
                                     "--out", str(out)])
        assert result.exit_code == 0, result.output
        (ours,) = json.loads((out / "metrics.json").read_text())["configs"].values()
        for metric in ("average_error_m", "ate_rmse_m", "closure_error_m"):
            assert ours[metric] == pytest.approx(run[name]["vs_gps"][metric], abs=0.01), (name, metric)
    # the body origin instead is 1.8 m below the antenna: what eval compared before
    result = runner.invoke(app, ["eval", str(results / "trajectory_full.tum"), str(results / "gps_fixes.csv"),
                                 "--lever-arm", "0,0,0", "--out", str(tmp_path / "origin")])
    (origin,) = json.loads((tmp_path / "origin" / "metrics.json").read_text())["configs"].values()
    assert origin["average_error_m"] > run["full"]["vs_gps"]["average_error_m"] + 0.1


def test_view_serves_a_saved_run_on_localhost_until_serve_for_ends(results):
    import subprocess
    import sys
    import urllib.request

    exe = Path(sys.executable).parent / "pancam-graph"
    view = subprocess.Popen([str(exe), "view", str(results), "--rerun", "serve", "--serve-for", "3"],
                            stderr=subprocess.PIPE, text=True)
    try:
        line = view.stderr.readline()
        assert "web viewer at http://127.0.0.1:" in line and "?url=rerun%2Bhttp" in line, line
        with urllib.request.urlopen(line.split("web viewer at ", 1)[1].split()[0], timeout=10) as page:
            assert page.status == 200
        assert view.wait(timeout=60) == 0
        assert "ERROR" not in view.stderr.read()  # the stream let go of the server before it stopped
    finally:
        view.kill()
        view.wait()


def test_every_commands_help_ends_with_examples():
    """`--help` of every command ends with one to three examples, each a pancam-graph command line
    naming that command (kiss-icp's shows one per data type)."""
    names = [c.name for c in app.registered_commands]
    assert len(names) >= 12
    for name in names:
        result = runner.invoke(app, [name, "--help"])
        assert result.exit_code == 0, name
        tail = result.output.rstrip().split("Examples:")
        assert len(tail) == 2, f"{name}: no examples"
        lines = [line.strip() for line in tail[1].strip().splitlines()]
        assert 1 <= len(lines) <= 3 and all(line.startswith("pancam-graph ") for line in lines), (name, lines)
        assert any(line.split()[1] == name for line in lines), (name, lines)
