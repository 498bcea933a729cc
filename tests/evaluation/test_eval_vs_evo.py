"""`pancam-graph eval` against evo on two real trajectory pairs: APE RMSE after SE(3) alignment
and RPE over a fixed distance agree to 1e-6 relative.

Pair 1, the robot_localization Husky bag: its wheel odometry against our odometry + GPS fusion.
Pair 2, KITTI drive 0001: OXTS velocities integrated (dead reckoning) against the OXTS poses.
Both come from `pancam-graph run` on the recording, so the run's writers are in the loop too.
"""

import copy
import json
from pathlib import Path

import pytest
from evo import main_ape, main_rpe
from evo.core import sync
from evo.core.metrics import PoseRelation, Unit
from evo.tools import file_interface
from typer.testing import CliRunner

from pancam_graph.cli import app

pytestmark = [pytest.mark.real_data, pytest.mark.slow]

REAL = Path(__file__).parents[1] / "data" / "real"
BAG = REAL / "robot_localization" / "test1.bag"
KITTI = REAL / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
runner = CliRunner()


def _run(source: Path, out: Path, *args: str) -> Path:
    result = runner.invoke(app, ["run", str(source), "--out", str(out), *args])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    base = tmp_path_factory.mktemp("recorded")
    bag = _run(BAG, base / "bag", "--odom-topic", "/husky_velocity_controller/odom")
    kitti = _run(KITTI, base / "kitti")
    return {
        "husky": (bag / "trajectory_dead_reckoning.tum", bag / "trajectory_dead_reckoning_gps.tum", 20.0),
        "kitti": (kitti / "trajectory_dead_reckoning.tum", kitti / "truth.tum", 10.0),
    }


def _evo(est: Path, ref: Path, delta_m: float) -> tuple[float, float, float]:
    traj_ref, traj_est = sync.associate_trajectories(file_interface.read_tum_trajectory_file(str(ref)),
                                                     file_interface.read_tum_trajectory_file(str(est)),
                                                     max_diff=0.01)
    ape = main_ape.ape(traj_ref, traj_est, PoseRelation.translation_part, align=True, correct_scale=False)
    # main_rpe.rpe reduces the trajectories it is given to the pair ends: one copy per call.
    rpe = {relation: main_rpe.rpe(copy.deepcopy(traj_ref), copy.deepcopy(traj_est), relation, delta=delta_m,
                                  delta_unit=Unit.meters, all_pairs=False, pairs_from_reference=True).stats["rmse"]
           for relation in (PoseRelation.translation_part, PoseRelation.rotation_angle_deg)}
    return ape.stats["rmse"], rpe[PoseRelation.translation_part], rpe[PoseRelation.rotation_angle_deg]


@pytest.mark.parametrize("name", ["husky", "kitti"])
def test_eval_agrees_with_evo(pairs, name, tmp_path):
    est, ref, delta_m = pairs[name]
    result = runner.invoke(app, ["eval", str(est), str(ref), "--align", "se3", "--rpe-delta", str(delta_m),
                                 "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "metrics.json").read_text())
    ours = document["configs"][est.stem]
    ape, rpe_t, rpe_r = _evo(est, ref, delta_m)
    assert ours["ate_alignment"] == "se3" and ours["rpe_pairs"] >= 5
    assert ours["ate_rmse_m"] == pytest.approx(ape, rel=1e-6)
    assert ours["rpe_translation_rmse_m"] == pytest.approx(rpe_t, rel=1e-6)
    assert ours["rpe_rotation_rmse_deg"] == pytest.approx(rpe_r, rel=1e-6)
    # The comparison is not trivial: the two tracks really differ.
    assert ape > 0.05 and rpe_t > 0.05
    assert (tmp_path / "eval.png").stat().st_size > 10_000


def test_recorded_runs_write_the_exports_and_score_held_out_fixes(pairs):
    bag = pairs["husky"][0].parent
    document = json.loads((bag / "metrics.json").read_text())
    fused = document["configs"]["dead_reckoning_gps"]["vs_held_out_gps"]
    odometry = document["configs"]["dead_reckoning"]["vs_held_out_gps"]
    assert fused["held_out_fixes"] == 197
    assert fused["rms_2d_m"] <= 1.3 * fused["stated_drms_m"] and fused["rms_2d_m"] <= 0.4 * odometry["rms_2d_m"]
    for suffix in (".tum", ".kitti", "_wgs84.csv", ".geojson", ".kml"):
        assert (bag / f"trajectory_dead_reckoning_gps{suffix}").stat().st_size > 1000
    # the same kinds of files as a scenario run: plots, report, the resolved configuration
    for name in ("report.md", "trajectories.png", "error_vs_distance.png", "run.toml", "reproduce.sh"):
        assert (bag / name).stat().st_size > 100, name
    kitti = json.loads((pairs["kitti"][0].parent / "metrics.json").read_text())
    # RTK-grade OXTS: the fused track sits within centimetres of the fixes it never saw.
    assert kitti["configs"]["dead_reckoning_gps"]["vs_held_out_gps"]["rms_2d_m"] < 0.05


def test_eval_of_a_gps_log_needs_the_trajectories_origin(pairs, tmp_path):
    est = pairs["husky"][1]
    result = runner.invoke(app, ["eval", str(est), str(est.parent / "gps_fixes.csv"), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output  # origin from local_frame.json beside the estimate
    ours = json.loads((tmp_path / "metrics.json").read_text())["configs"][est.stem]
    assert 0.5 < ours["average_error_2d_m"] < 2.0 and ours["rpe_pairs"] == 0
    lone = tmp_path / "lone.tum"
    lone.write_text(est.read_text())
    result = runner.invoke(app, ["eval", str(lone), str(est.parent / "gps_fixes.csv")])
    assert result.exit_code == 2 and "give --origin LAT,LON,H" in result.output


def test_eval_names_bad_files(tmp_path):
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0.5 0.5\n")
    good = tmp_path / "good.tum"
    good.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    result = runner.invoke(app, ["eval", str(bad), str(good)])
    assert result.exit_code == 2 and "bad.tum: pose 2: quaternion (qx qy qz qw) has norm 0.7071" in result.output
    late = tmp_path / "late.tum"
    late.write_text("100 0 0 0 0 0 0 1\n101 1 0 0 0 0 0 1\n")
    result = runner.invoke(app, ["eval", str(late), str(good)])
    assert result.exit_code == 2 and "0 poses matched within 0.01 s" in result.output
    # NaN passed the rotation check and failed only after the whole run (issue 15)
    nan = tmp_path / "nan.kitti"
    nan.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n")
    result = runner.invoke(app, ["eval", str(nan), str(nan)])
    assert result.exit_code == 2 and "nan.kitti: pose 2: a value that is not a finite number" in result.output


def test_view_replays_a_recorded_drive(pairs, tmp_path):
    bag = pairs["husky"][0].parent
    result = runner.invoke(app, ["view", str(bag), "--rerun", f"save:{tmp_path / 'bag.rrd'}"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "bag.rrd").stat().st_size > 100_000


def test_eval_refuses_a_standing_reference_and_a_zero_rpe_distance(tmp_path):
    still = tmp_path / "still.tum"
    still.write_text("".join(f"{t} 1 2 3 0 0 0 1\n" for t in range(5)))
    moving = tmp_path / "moving.tum"
    moving.write_text("".join(f"{t} {t} 0 0 0 0 0 1\n" for t in range(5)))
    result = runner.invoke(app, ["eval", str(moving), str(still)])
    assert result.exit_code == 2 and "still.tum: the reference stands still over the 5 matched poses" in result.output
    result = runner.invoke(app, ["eval", str(moving), str(moving), "--rpe-delta", "0"])
    assert result.exit_code == 2 and "--rpe-delta 0: the relative pose error's distance must be more" in result.output
