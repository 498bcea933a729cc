"""`pancam-graph sweep` on a local Dask cluster (issue 16): one results folder per run, a run
that fails is recorded while the others finish, a second invocation skips what is done, and
the reducer's efficiency and ANEES are bench --monte-carlo's."""

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError
from pancam_graph.evaluation.consistency import last_stop_summary, monte_carlo_summary
from pancam_graph.solve.pipeline import RunOptions, run_scenario
from pancam_graph.sweep.spec import SweepSpec, plan

pytestmark = pytest.mark.slow

EXE = Path(sys.executable).parent / "pancam-graph"
SPEC = """
scenarios = ["short_trail", "no_gps.toml"]
seeds = 2
configs = ["full"]
"""


def _sweep(tmp_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(EXE), "sweep", "spec.toml", "--out", "sweep", "--workers", "2", "--quiet"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)


def _rows(path: Path) -> list[dict]:
    with path.open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweep")
    (folder / "spec.toml").write_text(SPEC)
    # a scenario whose GPS is out over the whole path: the plan cannot see that (its [gps] is on), so
    # its `full` runs fail when they find no fix ("this traverse cannot feed it")
    no_gps = resolve_scenario("short_trail").read_text().replace('name = "short_trail"', 'name = "no_gps"')
    (folder / "no_gps.toml").write_text(no_gps + "\n[gps]\ndropouts = [[0.0, 100000.0]]\n")
    return folder, _sweep(folder)


def test_a_failing_run_is_recorded_and_the_others_finish(swept):
    folder, first = swept
    assert first.returncode == 1, first.stderr
    assert "2 done, 0 skipped, 2 failed" in first.stderr
    status = {r["run"]: r for r in _rows(folder / "sweep" / "runs_status.csv")}
    assert {r["status"] for n, r in status.items() if n.startswith("short_trail")} == {"done"}
    for name in ("no_gps-exomars-default-seed0", "no_gps-exomars-default-seed1"):
        assert status[name]["status"] == "failed" and "cannot feed it" in status[name]["message"]
    for seed in (0, 1):
        run = folder / "sweep" / "runs" / f"short_trail-exomars-default-seed{seed}"
        assert (run / "metrics.json").is_file() and (run / "report.md").is_file()
        assert not list(run.glob("*.png"))  # sweep runs skip the figures (--no-plots)


@pytest.fixture(scope="module")
def serial():
    """full over seeds 0 and 1 of short_trail as bundled (what the sweep and bench run), one after
    another in this process, and their last stops' NEES."""
    scenario = load_scenario(resolve_scenario("short_trail"))
    results = [run_scenario(scenario, RunOptions(seed=s, configs=("full",))).configurations["full"]
               for s in (0, 1)]
    return monte_carlo_summary([c.consistency for c in results]) | {
        "nees_last": last_stop_summary([c.nees.last for c in results])["nees_last"]}


def test_the_summary_is_bench_monte_carlos(swept, serial):
    folder, _ = swept
    (summary,) = _rows(folder / "sweep" / "summary.csv")
    assert (summary["scenario"], summary["config"], summary["runs"]) == ("short_trail", "full", "2")
    assert float(summary["efficiency"]) == pytest.approx(serial["efficiency"], rel=1e-9)
    assert float(summary["anees"]) == pytest.approx(serial["anees"], rel=1e-9)
    assert float(summary["nees_last"]) == pytest.approx(serial["nees_last"], rel=1e-9)
    assert summary["last_stop_covariance"] in ("consistent", "under-confident", "over-confident")


def test_bench_monte_carlo_runs_as_a_sweep_with_workers(tmp_path, serial):
    result = subprocess.run([str(EXE), "bench", "short_trail", "--monte-carlo", "2", "--workers", "2"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["seeds"] == [0, 1] and report["workers"] == 2
    assert report["monte_carlo"]["full"]["efficiency"] == pytest.approx(serial["efficiency"], rel=1e-9)
    assert report["monte_carlo"]["full"]["anees"] == pytest.approx(serial["anees"], rel=1e-9)
    assert report["monte_carlo"]["full"]["last_stop"]["nees_last"] == pytest.approx(serial["nees_last"], rel=1e-9)


def test_a_second_invocation_skips_the_runs_done(swept):
    folder, _ = swept
    again = _sweep(folder)
    assert "0 done, 2 skipped, 2 failed" in again.stderr, again.stderr
    assert len(_rows(folder / "sweep" / "runs.csv")) == 2  # the two done runs, read back


def test_a_bad_spec_names_the_field(tmp_path):
    (tmp_path / "spec.toml").write_text('scenarios = ["short_trail"]\nseeds = 0\n')
    result = _sweep(tmp_path)
    assert result.returncode == 2 and "spec.toml: invalid sweep specification" in result.stderr
    assert "field 'seeds'" in result.stderr and "Traceback" not in result.stderr


def test_two_scenario_files_of_one_name_are_refused(tmp_path):
    # They would share their results folders and their rows of the table.
    (tmp_path / "copy.toml").write_text(resolve_scenario("short_trail").read_text())
    spec = SweepSpec(scenarios=["short_trail", "copy.toml"], seeds=1)
    with pytest.raises(ConfigError, match="short_trail and copy.toml are both named 'short_trail'"):
        plan(spec, tmp_path / "sweep", tmp_path)


@pytest.mark.parametrize("text,words", [
    ('scenarios = ["short_trail"]\nconfigs = ["vo", "lidar"]\n', "sweep: configs 'lidar' (short_trail, variant "
     "default): unknown kind 'lidar'"),
    ('scenarios = ["short_trail", "nope"]\n', "unknown scenario 'nope'"),
])
def test_a_bad_specification_is_refused_before_anything_is_written(tmp_path, text, words):
    from pancam_graph.api import plan_sweep
    from pancam_graph.errors import ConfigError

    (tmp_path / "spec.toml").write_text(text)
    with pytest.raises(ConfigError, match=re.escape(words)):
        plan_sweep(tmp_path / "spec.toml", tmp_path / "sweep")
    assert not (tmp_path / "sweep").exists()  # no scenarios/ folder left behind, no Dask run started


@pytest.mark.parametrize("address, words", [
    ("not a url", r"--scheduler 'not a url': not a scheduler address like tcp://host:8786"),
    ("tcp://127.0.0.1:{closed}", r"--scheduler tcp://127.0.0.1:\d+: nothing answers there"),
])
def test_a_scheduler_that_is_not_there_is_refused_at_once_leaving_nothing(tmp_path, address, words):
    import socket

    from typer.testing import CliRunner

    from pancam_graph.cli import app

    with socket.socket() as probe:  # a port that was free a moment ago: nothing listens on it
        probe.bind(("127.0.0.1", 0))
        closed = probe.getsockname()[1]
    spec = tmp_path / "spec.toml"
    spec.write_text('scenarios = ["short_trail"]\nconfigs = ["vo"]\n')
    result = CliRunner().invoke(app, ["sweep", str(spec), "--out", str(tmp_path / "sw"), "--scheduler",
                                      address.format(closed=closed), "--quiet"])
    assert result.exit_code == 2, result.output
    assert re.search(words, result.output.replace("\n", " ")), result.output
    assert not (tmp_path / "sw").exists()


def test_a_configuration_a_scenario_cannot_feed_is_refused_before_anything_is_written(tmp_path):
    spec = SweepSpec(scenarios=["short_trail", "mars_excerpt"], configs=["full_mars"])
    with pytest.raises(ConfigError, match=r"configs 'full_mars' cannot run on short_trail .*orbital: the scenario "
                                          r"simulates no orbital maps"):
        plan(spec, tmp_path / "sw")
    assert not (tmp_path / "sw").exists()


@pytest.mark.parametrize("name", ["short_trail", "mars_excerpt"])
def test_what_a_scenario_can_feed_is_what_its_simulation_feeds(name):
    """The check made before simulating (kinds.scenario_unavailable) against the one made on the
    simulated traverse (kinds.unavailable), for every defined configuration."""
    from pancam_graph.config import load_scenario
    from pancam_graph.kinds import scenario_unavailable, unavailable
    from pancam_graph.sim import simulate

    scenario = load_scenario(resolve_scenario(name))
    traverse, _ = simulate(scenario, 0)
    for config, kinds in scenario.estimator.configurations.items():
        before, after = scenario_unavailable(kinds, scenario), unavailable(kinds, traverse)
        assert (before is None) == (after is None), (config, before, after)
