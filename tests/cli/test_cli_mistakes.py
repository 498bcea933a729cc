"""Every user mistake exits 2 with one line naming the argument, writes nothing and shows no
traceback. The mistakes go through the command-line application in this process (each in a
process of its own cost a second of imports, 20 s of the suite); that the installed console
script says the same, exit code and words, is checked on a few of them in real processes, as is
everything that needs one (two runs at once, a viewer, a dead run)."""

import os
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REAL = Path(__file__).parents[1] / "data" / "real"
BAG = REAL / "robot_localization" / "test1.bag"
DATE_FOLDER = REAL / "kitti_raw" / "2011_09_26"


def _cli(*args: str, cwd: Path, env: dict | None = None, timeout_s: float = 300.0) -> subprocess.CompletedProcess:
    """The CLI in a process of its own; a hang ends the test (TimeoutExpired) after `timeout_s`,
    which is no speed target: a busy machine is slow, not hung."""
    exe = Path(sys.executable).parent / "pancam-graph"
    return subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True, timeout=timeout_s,
                          env={**os.environ, **(env or {})})


def _assert_usage_error(result: subprocess.CompletedProcess, *words: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    for word in words:
        assert word in result.stderr, (word, result.stderr)


MISTAKES = [
    (["run", "short_trail", "--out", "a_file"], ["--out", "is a file"]),
    (["run", "short_trail", "--seed", "-1"], ["Invalid value for '--seed'", "greater than or equal to 0"]),
    (["run", str(DATE_FOLDER)], ["KITTI date folder", "2011_09_26_drive_0001_sync"]),
    (["run", "short_trail", "--gps-topic", "/fix"], ["--gps-topic does not apply to a scenario"]),
    (["run", str(BAG), "--seed", "3"], ["--seed does not apply to a rosbag"]),
    (["run", str(BAG), "--stereo-topics", "/left"], ["--stereo-topics '/left': expected LEFT,RIGHT"]),
    (["run", "short_trail", "--detector", "surf"], ["--detector 'surf': expected gftt, orb or sift"]),
    (["run", "short_trail", "--errors", "harsh"], ["--errors 'harsh': expected ideal or realistic"]),
    (["simulate", "short_trail", "--out", "sim", "--errors", "harsh"], ["--errors 'harsh': expected ideal or "]),
    (["render", "short_trail", "--out", "img", "--errors", "harsh"], ["--errors 'harsh': expected ideal or "]),
    (["run", str(BAG), "--errors", "ideal"], ["--errors does not apply to a rosbag"]),
    (["track", "no_images", "--out", "t", "--detector", "surf"], ["--detector 'surf'"]),
    (["run", "short_trail", "--holdout-every", "-2"], ["Invalid value for '--holdout-every'"]),
    (["run", "short_trail", "--configs", "vo+lidar"], ["--configs vo+lidar", "'lidar'"]),
    (["run", "short_trail", "--configs", "vo_site"], ["--configs vo_site", "did you mean vo_sites?"]),
    (["run", "short_trail", "--configs", "hrc+vo"], ["'hrc' needs 'sites' (it adds views of the site landmarks)"]),
    (["run", "no_such_scenario"], ["unknown scenario 'no_such_scenario'"]),
    (["run", "a_file"], ["a_file: not a source: expected", "a scenario TOML file"]),
    (["run", "short_trail", "--rerun", "spawn"], ["--rerun spawn: no display"]),
    (["analyze", "--out", "full_folder"], ["--out full_folder", "not empty"]),
    (["simulate", "short_trail", "--out", "full_folder"], ["full_folder", "not empty"]),
    (["run", "bracket[/x].toml"], ["bracket[/x].toml"]),
    (["run", "short_trail", "--resume", "full_folder"], ["--resume goes on with the run's own source", "SOURCE"]),
    (["run", "--resume", "full_folder"], ["--resume full_folder", "<out>.partial"]),
    (["run", "--resume", "empty.partial"], ["empty.partial: has no checkpoint", "start the run again"]),
    (["eval", "a_file", "a_file", "--origin", "95,10,0"], ["--origin 95,10,0: origin out of range: lat 95"]),
    (["eval", "a_file", "a_file", "--origin", "north"], ["--origin 'north': expected LAT,LON,H"]),
]


def _make_work_folder(folder: Path) -> list[Path]:
    """What a mistake must leave untouched: a file, a folder with a file, an empty .partial."""
    folder.mkdir()
    (folder / "a_file").write_text("not a folder")
    (folder / "full_folder").mkdir()
    (folder / "full_folder" / "keep.txt").write_text("mine")
    (folder / "empty.partial").mkdir()
    return sorted(p.relative_to(folder) for p in folder.rglob("*"))


def _app(*args: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """The command-line application run here, in `cwd`, as the console script runs it; an
    exception that escapes it is shown as the traceback a user would see."""
    import traceback

    from typer.testing import CliRunner

    from pancam_graph.cli.app import app

    here = os.getcwd()
    os.chdir(cwd)
    try:
        result = CliRunner().invoke(app, list(args), env=env, prog_name="pancam-graph")
    finally:
        os.chdir(here)
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "".join(traceback.format_exception(result.exception))
    return subprocess.CompletedProcess(args, result.exit_code, result.stdout, stderr)


@pytest.mark.parametrize("case", range(len(MISTAKES)), ids=[" ".join(args[:2]) for args, _ in MISTAKES])
def test_mistake_exits_2_names_the_argument_and_writes_nothing(case, tmp_path):
    folder = tmp_path / "work"
    before = _make_work_folder(folder)
    result = _app(*MISTAKES[case][0], cwd=folder, env={"DISPLAY": ""})
    _assert_usage_error(result, *MISTAKES[case][1])
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
    assert len(result.stderr.strip().splitlines()) <= 4  # a short message (click adds usage lines), not a dump


@pytest.mark.parametrize("case", [0, 1, 12, 21], ids=lambda case: " ".join(MISTAKES[case][0][:2]))
def test_the_console_script_says_what_the_application_says(case, tmp_path):
    """A typed error (an --out that is a file, an unknown scenario, a bad --origin) and a click
    usage error (a negative --seed): the installed command's exit code and words are the
    in-process application's."""
    folder = tmp_path / "work"
    before = _make_work_folder(folder)
    script = _cli(*MISTAKES[case][0], cwd=folder, env={"DISPLAY": ""})
    here = _app(*MISTAKES[case][0], cwd=folder, env={"DISPLAY": ""})
    _assert_usage_error(script, *MISTAKES[case][1])
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
    assert (script.returncode, script.stderr.split()) == (here.returncode, here.stderr.split())


def test_view_without_a_display_saves_the_replay_and_says_so(tmp_path):
    """A headless machine: a folder that is no run is named first; by default the replay is saved
    beside the results with one line saying where; an explicit spawn is refused before it would
    wait for a viewer that never comes."""
    headless = {"DISPLAY": "", "WAYLAND_DISPLAY": ""}
    result = _cli("view", str(tmp_path / "nowhere"), cwd=tmp_path, env=headless)
    _assert_usage_error(result, "nowhere: not a results folder")
    ran = _cli("run", "short_trail", "--configs", "vo", "--out", "res", "--quiet", "--no-plots", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    result = _cli("view", "res", cwd=tmp_path, env=headless)
    assert result.returncode == 0, result.stderr
    assert "no display: the replay is saved to res/replay.rrd" in " ".join(result.stderr.split())
    assert (tmp_path / "res" / "replay.rrd").stat().st_size > 10_000
    result = _cli("view", "res", "--rerun", "spawn", cwd=tmp_path, env=headless)
    _assert_usage_error(result, "no display", "--rerun save", "--rerun serve")


def test_version_and_help(tmp_path):
    result = _cli("--version", cwd=tmp_path)
    assert result.returncode == 0 and result.stdout.startswith("pancam-graph ")
    result = _cli("run", "--help", cwd=tmp_path)
    assert result.returncode == 0 and "--configs" in result.stdout


def test_the_default_results_folder_is_the_one_help_names(tmp_path):
    import re

    helped = " ".join(_cli("run", "--help", cwd=tmp_path, env={"COLUMNS": "200"}).stdout.split())
    assert "results/<name>-seed<N>-<YYYYmmdd-HHMMSS> for a scenario" in helped
    result = _cli("run", "short_trail", "--configs", "vo", "--quiet", "--no-plots", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (made,) = (tmp_path / "results").iterdir()
    assert re.fullmatch(r"short_trail-seed0-\d{8}-\d{6}", made.name), made.name


def test_show_config_prints_the_resolved_scenario(tmp_path):
    import tomllib

    result = _cli("show-config", "short_trail", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    resolved = tomllib.loads(result.stdout)
    assert resolved["name"] == "short_trail"
    # the realistic profile, as bundled, estimates the stereo calibration wherever VO or sites are
    assert resolved["errors"]["profile"] == "realistic"
    assert resolved["estimator"]["configurations"]["full"] == ["vo", "sites", "hrc", "gps", "stereo_calibration"]
    assert resolved["estimator"]["sites"]["memory"] == 3  # every constant, defaults included


def test_show_config_reads_like_the_readmes_example_a_waypoint_a_line_and_comments_from_the_fields():
    import tomllib

    from pancam_graph.config import Scenario, dump_scenario, load_scenario, resolve_scenario

    scenario = load_scenario(resolve_scenario("mars_traverse"))
    text = dump_scenario(scenario)
    assert Scenario.model_validate(tomllib.loads(text)) == scenario  # the comments change nothing
    lines = text.splitlines()
    waypoints = lines.index("waypoints = [")
    assert lines[waypoints + 1] == "    [0.0, 0.0, 0.0],"  # a waypoint a line, not a number a line
    assert len(lines) < len(scenario.path.waypoints) + 400, len(lines)  # was 469 with about 230 number lines
    # each field's description above it, each table's docstring above the table
    assert lines[lines.index("points_per_site = 150") - 1] == "# tie points kept per site"
    assert lines[lines.index("[estimator.orbital]") - 1] == "# How sites are registered to the orbital maps."


def test_two_runs_on_one_out_exactly_one_wins_and_nothing_is_lost(tmp_path):
    exe = Path(sys.executable).parent / "pancam-graph"
    first = subprocess.Popen([str(exe), "run", "short_trail", "--out", "res", "--quiet"], cwd=tmp_path,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300  # a bound on a wait, not a speed target
    while not (tmp_path / "res.partial" / ".lock").exists() and first.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    second = _cli("run", "short_trail", "--out", "res", "--quiet", cwd=tmp_path)
    assert first.poll() is None  # refused while the first still runs, not after it (whatever the load)
    _assert_usage_error(second, "in use by run", "choose another --out")
    out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    assert (tmp_path / "res" / "metrics.json").is_file() and (tmp_path / "res" / "report.md").is_file()
    assert not (tmp_path / "res.partial").exists()


def test_a_dead_runs_partial_folder_is_kept(tmp_path):
    dead = tmp_path / "res.partial"
    dead.mkdir()
    (dead / ".lock").write_text("999999999\n")  # no such process
    (dead / "steps.csv").write_text("what the dead run computed\n")
    result = _cli("run", "short_trail", "--out", "res", "--quiet", "--configs", "vo", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "res.partial.1" / "steps.csv").read_text() == "what the dead run computed\n"
    assert (tmp_path / "res" / "metrics.json").is_file()


@contextmanager
def _nothing_listening():
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    yield port


@contextmanager
def _silent_listener():
    """Accepts every connection and never says a word (a stalled viewer, a wrong port)."""
    held = []
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        threading.Thread(target=lambda: [held.append(server.accept()) for _ in range(8)], daemon=True).start()
        yield server.getsockname()[1]


@contextmanager
def _web_server():
    """An HTTP server that is not a viewer."""
    import http.server

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("viewer,said", [(_nothing_listening, "no viewer answers"),
                                         (_silent_listener, "does not answer within 3 s"),
                                         (_web_server, "is not a rerun viewer")])
def test_a_viewer_that_does_not_answer_is_a_warning_not_a_hang(tmp_path, viewer, said):
    """rerun's gRPC client waits for ever on a listener that does not answer: such a viewer is
    found out before the run and left out with a warning; the run finishes with its results."""
    with viewer() as port:  # a hang would end in _cli's timeout
        result = _cli("run", "short_trail", "--out", "res", "--quiet", "--configs", "vo",
                      "--rerun", f"connect:rerun+http://127.0.0.1:{port}/proxy", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr and result.stderr.count("warning:") == 1
    assert said in result.stderr and (tmp_path / "res" / "metrics.json").is_file()


def test_a_folder_named_like_a_bundled_scenario_is_named_as_what_hides_it(tmp_path):
    """`render short_trail --out short_trail` leaves a folder that a later `run short_trail` or
    `show-config short_trail` in the same place would take for the argument."""
    (tmp_path / "short_trail").mkdir()
    (tmp_path / "short_trail" / "notes.txt").write_text("not a source")
    result = _app("run", "short_trail", cwd=tmp_path, env={"DISPLAY": ""})
    _assert_usage_error(result, "short_trail: not a source", "hides the bundled scenario", "short_trail.toml")
    # a scenario command takes no folder: the name is the bundled scenario's
    shown = _app("show-config", "short_trail", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert 'name = "short_trail"' in shown.stdout
    (tmp_path / "not_a_scenario").mkdir()
    _assert_usage_error(_app("show-config", "not_a_scenario", cwd=tmp_path),
                        "not_a_scenario: a folder, not a scenario TOML file")
