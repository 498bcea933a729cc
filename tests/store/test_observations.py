"""The observation-level input format: a scenario's own observations, written as an observation
folder and run through `pancam-graph run FOLDER`, give the scenario run's metrics exactly; bad
files are named with their line and column."""

import json
import shutil

import pytest
import yaml
from typer.testing import CliRunner

from pancam_graph.cli import app
from pancam_graph.errors import InputError
from pancam_graph.store.observation_folder import read_observations

pytestmark = pytest.mark.slow

runner = CliRunner()
SEED = "3"


def _invoke(*args: str) -> None:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    base = tmp_path_factory.mktemp("observations")
    _invoke("run", "short_trail", "--seed", SEED, "--out", str(base / "scenario_run"), "--quiet")
    _invoke("simulate", "short_trail", "--seed", SEED, "--out", str(base / "observations"))
    _invoke("run", str(base / "observations"), "--out", str(base / "observation_run"), "--quiet")
    return base


def _metrics(folder):
    document = json.loads((folder / "metrics.json").read_text())
    for config in document["configs"].values():
        config.pop("isam2_update_ms")
    return document


def test_observation_folder_reproduces_the_scenario_run_exactly(folders):
    scenario, observed = _metrics(folders / "scenario_run"), _metrics(folders / "observation_run")
    assert observed["vo"] == scenario["vo"]
    assert observed["configs"]["vo"] == scenario["configs"]["vo"]  # every field, bit for bit
    assert observed["configs"]["vo"]["relative_closure_pct"] > 0.01  # a real estimate, not a copy of truth
    # Sites, HRC, GPS and dead reckoning travel through the format too, bit for bit, and so do
    # the consistency fields (truth_landmarks.csv and truth.toml carry what the bound needs).
    for name in ("vo_sites", "full", "dead_reckoning"):
        assert observed["configs"][name]["efficiency"] > 0.3, name
    assert observed["configs"] == scenario["configs"]
    assert (observed["stops"], observed["sites"], observed["gps_fixes"]) == (
        scenario["stops"], scenario["sites"], scenario["gps_fixes"])


def _copy(folders, tmp_path):
    folder = tmp_path / "obs"
    shutil.copytree(folders / "observations", folder)
    return folder


def test_observation_file_with_a_missing_column_is_named(folders, tmp_path):
    folder = _copy(folders, tmp_path)
    lines = (folder / "stereo.csv").read_text().splitlines()
    (folder / "stereo.csv").write_text("\n".join(",".join(line.split(",")[:5] + line.split(",")[6:])
                                                 for line in lines) + "\n")
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(folder), "--out", str(out), "--quiet"])
    assert result.exit_code == 2
    assert "stereo.csv: line 1: missing column(s) u_right (expected stop,time_s,track,u_left,u_right,v)" in " ".join(
        result.output.split())
    assert not out.exists()


def test_bad_values_name_file_line_and_column(folders, tmp_path):
    folder = _copy(folders, tmp_path)
    lines = (folder / "odometry.csv").read_text().splitlines()
    fields = lines[3].split(",")
    fields[5] = "north"
    lines[3] = ",".join(fields)
    (folder / "odometry.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(Exception, match=r"odometry.csv: line 4: column 'r22': expected a number, got 'north'"):
        read_observations(folder)
    folder = _copy(folders, tmp_path / "b")
    lines = (folder / "gps.csv").read_text().splitlines()
    lines.insert(3, lines[1])  # an earlier fix again: time goes back
    (folder / "gps.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(Exception, match=r"gps.csv: line 4: time_s [\d.]+ does not increase \(previous fix [\d.]+\)"):
        read_observations(folder)


def test_rows_shorter_than_the_header_say_what_they_lack(folders, tmp_path):
    """Rows written without the newer dwell_s field under a header that has it."""
    folder = _copy(folders, tmp_path)
    header, *rows = (folder / "stereo.csv").read_text().splitlines()
    assert header == "stop,time_s,dwell_s,track,u_left,u_right,v"
    rows = [",".join(f for i, f in enumerate(row.split(",")) if i != 2) for row in rows]
    (folder / "stereo.csv").write_text("\n".join([header, *rows]) + "\n")
    with pytest.raises(InputError) as refused:
        read_observations(folder)
    assert str(refused.value) == (f"{folder / 'stereo.csv'}: line 2: 6 fields, no v (the header names 7 columns: "
                                  "stop,time_s,dwell_s,track,u_left,u_right,v)")


def test_rig_from_a_calibration_file(folders, tmp_path):
    """An external front-end brings its own calibration instead of a preset (Kalibr here)."""
    folder = _copy(folders, tmp_path)
    preset = read_observations(folder).traverse.rig
    cam = {"camera_model": "pinhole", "intrinsics": [preset.wac.fx, preset.wac.fy, preset.wac.cx, preset.wac.cy],
           "distortion_model": "radtan", "distortion_coeffs": [0.0] * 4,
           "resolution": [preset.wac.width, preset.wac.height]}
    t = [[1.0, 0, 0, -preset.baseline_m], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    (folder / "camchain.yaml").write_text(yaml.safe_dump({"cam0": cam, "cam1": {**cam, "T_cn_cnm1": t}}))
    manifest = (folder / "traverse.toml").read_text().replace('preset = "exomars"', 'calibration = "camchain.yaml"')
    (folder / "traverse.toml").write_text(manifest)
    rig = read_observations(folder).traverse.rig
    assert rig.baseline_m == pytest.approx(preset.baseline_m, rel=1e-12)
    assert (rig.wac.fx, rig.wac.cx) == pytest.approx((preset.wac.fx, preset.wac.cx), rel=1e-9)


def test_manifest_field_errors_are_named(folders, tmp_path):
    folder = _copy(folders, tmp_path)
    text = (folder / "traverse.toml").read_text()
    (folder / "traverse.toml").write_text(text.replace("image_noise_px = 0.3\n", "image_noise_px = -1.0\n"))
    with pytest.raises(Exception, match=r"traverse.toml: invalid observation manifest:\s+field 'image_noise_px': "
                                        r"Input should be greater than 0"):
        read_observations(folder)


def test_a_track_listed_twice_at_a_stop_names_its_line(folders, tmp_path):
    folder = _copy(folders, tmp_path)
    lines = (folder / "stereo.csv").read_text().splitlines()
    lines.insert(4, lines[2])  # line 3's observation again, as line 5
    (folder / "stereo.csv").write_text("\n".join(lines) + "\n")
    track = lines[2].split(",")[3]  # stop,time_s,dwell_s,track,...
    with pytest.raises(Exception, match=rf"stereo.csv: line 5: stop 0 lists track {track} a second time"):
        read_observations(folder)


def test_csv_files_with_a_byte_order_mark_and_crlf_read_the_same_and_other_bytes_are_named(folders, tmp_path):
    from pancam_graph.errors import InputError

    folder = _copy(folders, tmp_path)
    first = read_observations(folder).traverse
    for name in ("stereo.csv", "odometry.csv", "gps.csv"):
        text = (folder / name).read_text()
        (folder / name).write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    again = read_observations(folder).traverse
    assert len(again.stops) == len(first.stops) and len(again.gps_fixes) == len(first.gps_fixes)
    assert all((a.stereo.uvv == b.stereo.uvv).all() for a, b in zip(first.stops, again.stops, strict=True))
    lines = (folder / "gps.csv").read_bytes().split(b"\r\n")
    lines[2] = lines[2] + b"\xff\xfe"
    (folder / "gps.csv").write_bytes(b"\r\n".join(lines))
    with pytest.raises(InputError, match=r"gps.csv: not UTF-8 text"):
        read_observations(folder)
    (folder / "gps.csv").write_text("time_s," + "x" * 200_000 + "\n")
    with pytest.raises(InputError, match=r"gps.csv: line 1: not a CSV row this reader takes \(field larger"):
        read_observations(folder)


@pytest.mark.parametrize("old,new,words", [
    ("image_noise_px = 0.3\n", "image_noise_px = nan\n", "field 'image_noise_px': Input should be a finite number"),
    ("wheel_slip_sigma = ", "wheel_slip_sigma = inf\nx_old_slip = ", "field 'wheel_slip_sigma': Input should be a "
     "finite number"),
])
def test_manifest_numbers_must_be_finite(folders, tmp_path, old, new, words):
    from pancam_graph.errors import InputError

    folder = _copy(folders, tmp_path)
    text = (folder / "traverse.toml").read_text()
    assert old in text
    (folder / "traverse.toml").write_text(text.replace(old, new, 1))
    with pytest.raises(InputError) as error:
        read_observations(folder)
    assert words in " ".join(str(error.value).split())


@pytest.mark.parametrize("factor,words", [
    (0.0, "not a rotation"),  # a zero axis: once the smoother's indeterminate system at x0
    (2.0, "not a rotation"),  # a scale
    (-1.0, "det -1"),  # a reflection: orthonormal, but not a rotation
])
def test_a_start_pose_that_is_not_rigid_is_refused(folders, tmp_path, factor, words):
    import tomllib

    import tomli_w

    from pancam_graph.errors import InputError

    folder = _copy(folders, tmp_path)
    manifest = tomllib.loads((folder / "traverse.toml").read_text())
    manifest["start_world_T_body"][0][:3] = [factor * v for v in manifest["start_world_T_body"][0][:3]]
    (folder / "traverse.toml").write_text(tomli_w.dumps(manifest))
    with pytest.raises(InputError) as error:
        read_observations(folder)
    message = " ".join(str(error.value).split())
    assert "start_world_T_body" in message and words in message, message


def test_a_nan_in_truth_kitti_is_named_when_read_not_after_the_run(folders, tmp_path):
    from pancam_graph.errors import InputError

    folder = _copy(folders, tmp_path)
    lines = (folder / "truth.kitti").read_text().splitlines()
    fields = lines[4].split()
    fields[3] = "nan"
    lines[4] = " ".join(fields)
    (folder / "truth.kitti").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"truth.kitti: pose 5: a value that is not a finite number"):
        read_observations(folder)


@pytest.mark.parametrize("column,value,words", [
    ("stop", "-1", "stop -1 outside 0..9999999"),
    ("stop", "10000000000", "stop 10000000000 outside 0..9999999"),
    ("track", str(2**63), f"track {2**63} outside 0..2^63-1"),
])
def test_stop_and_track_numbers_out_of_range_are_named(folders, tmp_path, column, value, words):
    """An IndexError, all memory, an int64 overflow before (issue 15)."""
    import re

    from pancam_graph.errors import InputError

    folder = _copy(folders, tmp_path)
    lines = (folder / "stereo.csv").read_text().splitlines()
    fields = lines[5].split(",")
    fields[lines[0].split(",").index(column)] = value
    lines[5] = ",".join(fields)
    (folder / "stereo.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="stereo.csv: line 6: " + re.escape(words)):
        read_observations(folder)


def _edit_row(file, line, column, value):
    def edit(folder):
        lines = (folder / file).read_text().splitlines()
        fields = lines[line - 1].split(",")
        fields[lines[0].split(",").index(column)] = value
        lines[line - 1] = ",".join(fields)
        (folder / file).write_text("\n".join(lines) + "\n")
    return edit


def _no_fix(folder):
    for column, value in (("lat_deg", "0"), ("lon_deg", "0"), ("h_m", "0")):
        _edit_row("gps.csv", 3, column, value)(folder)


def _repeat_row(file, line, at):
    def edit(folder):
        lines = (folder / file).read_text().splitlines()
        lines.insert(at - 1, lines[line - 1])
        (folder / file).write_text("\n".join(lines) + "\n")
    return edit


@pytest.mark.parametrize("edit,words", [
    (_no_fix, "gps.csv: line 3: lat_deg = lon_deg = 0: a receiver's no-fix marker, not a position"),
    (_edit_row("gps.csv", 4, "lat_deg", "45.0"), "gps.csv: line 4: the fix lies 584 km from the traverse's origin "
                                                 "(at most 100 km): not a fix of this traverse"),
    (_edit_row("gps.csv", 4, "h_m", "1e308"), "gps.csv: line 4: h_m 1e+308: expected within 100 km of the ellipsoid"),
    (_edit_row("stereo.csv", 6, "u_left", "1e308"), "stereo.csv: line 6: column 'u_left' = 1e+308 px lies more "
                                                    "than an image size (1024 px) outside the image"),
    (_edit_row("hrc.csv", 6, "v", "-1e308"), "hrc.csv: line 6: column 'v' = -1e+308 px lies more than an image "
                                             "size"),
    (_repeat_row("panorama.csv", 3, 4), "panorama.csv: line 4: track {track} a second time in the frame at stop 0, "
                                        "pan -3.14159 rad, tilt -0.10472 rad (line 3): one row per track and frame"),
    (_edit_row("panorama.csv", 4, "site", "7"), "panorama.csv: line 4: site 7, but line 2 puts stop 0 at site 0: "
                                                "a stop's panorama is of one site"),
])
def test_rows_a_run_would_misuse_are_refused_in_one_line(folders, tmp_path, edit, words):
    """No-fix markers (once GPS errors of 353 km), pixels of 1e308 (numpy overflow warnings), a
    track twice in a panorama frame and a site that disagrees with its stop's were all accepted
    (issue 35): each is refused with one line, and nothing is written."""
    folder = _copy(folders, tmp_path)
    edit(folder)
    track = (folder / "panorama.csv").read_text().splitlines()[2].split(",")[4]
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(folder), "--out", str(out), "--quiet"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert words.format(track=track) in lines[0] and lines[0].startswith(f"error: {folder}")
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_tables_with_a_header_and_no_rows_read_as_nothing_seen(folders, tmp_path):
    folder = _copy(folders, tmp_path)
    for name in ("panorama.csv", "hrc.csv", "truth_landmarks.csv"):
        path = folder / name
        path.write_text(path.read_text().splitlines()[0] + "\n")
    obs = read_observations(folder)
    assert len(obs.traverse.stops) > 100
    assert not any(stop.panorama or stop.hrc or stop.is_site for stop in obs.traverse.stops)
    assert obs.truth.landmarks.shape == (0, 3)
