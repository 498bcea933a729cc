import json

import pytest
from typer.testing import CliRunner

from pancam_graph.cli import app

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
        (GOOD.replace("[path]", "[path]\nstop_spacing_m = [2.0, 1.0]"), "path"),
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


def test_run_writes_a_complete_results_folder(tmp_path):
    out = tmp_path / "res"
    result = runner.invoke(app, ["run", "short_trail", "--out", str(out), "--quiet", "--seed", "3"])
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert {"scenario.toml", "metrics.json", "truth.tum", "gps_fixes.csv", "trajectories.png",
            "error_vs_distance.png", "motions.csv"} <= names
    for config in ("vo", "vo_sites", "vo_sites_hrc", "full"):
        assert f"trajectory_{config}.tum" in names
    metrics = json.loads((out / "metrics.json").read_text())
    for config in metrics["configs"].values():
        for key in ("average_error_m", "closure_error_m", "relative_closure_pct", "ate_rmse_m",
                    "reference_length_m", "length_ratio", "bridged_stops"):
            assert isinstance(config[key], (int, float))
    assert {"median", "p99"} <= metrics["timing"]["isam2_update_ms"].keys()
    assert metrics["timing"]["wall_s"] > 0
    # the resolved scenario re-runs
    again = runner.invoke(app, ["run", str(out / "scenario.toml"), "--out", str(tmp_path / "again"),
                                "--quiet", "--seed", "3", "--no-gps"])
    assert again.exit_code == 0, again.output
    rerun = json.loads((tmp_path / "again" / "metrics.json").read_text())["configs"]["vo"]
    original = metrics["configs"]["vo"]
    for timing in (rerun, original):
        timing.pop("isam2_update_ms")
    assert rerun == original
    # a results folder is never overwritten
    clash = runner.invoke(app, ["run", "short_trail", "--out", str(out), "--quiet"])
    assert clash.exit_code == 1 and "not empty" in clash.output


def test_bench_prints_json():
    result = runner.invoke(app, ["bench", "short_trail"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["isam2_update_ms"]["median"] > 0
    assert report["isam2_update_ms"]["p99"] >= report["isam2_update_ms"]["median"]
    assert report["wall_s"] > 0 and report["peak_rss_mb"] > 0


def test_scenarios_lists_bundled_files():
    result = runner.invoke(app, ["scenarios"])
    assert result.exit_code == 0
    for name in ("denver_trail", "straight_500m", "gps_multipath", "short_trail"):
        assert name in result.output
