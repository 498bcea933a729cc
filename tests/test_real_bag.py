"""Real recorded data: the robot_localization Husky bag (wheel odometry + consumer GPS)."""

from pathlib import Path

import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.fusion import fuse_odometry_gps
from pancam_graph.io.rosbag import read_navsatfix, read_odometry

BAG = Path(__file__).parent / "data" / "real" / "robot_localization" / "test1.bag"
ODOM = "/husky_velocity_controller/odom"


@pytest.fixture(scope="module")
def bag():
    fixes, rejected = read_navsatfix(BAG, "/fix")
    return fixes, rejected, read_odometry(BAG, ODOM)


def test_reader_matches_the_published_description(bag):
    fixes, rejected, odom = bag
    assert len(fixes) == 989 and rejected == [] and len(odom) == 3952
    assert odom.times_s[-1] - odom.times_s[0] == pytest.approx(395, abs=1.0)
    assert all(0.6 <= f.sigma_horizontal_m**2 <= 2.9 for f in fixes)
    # wheel odometry alone ends about 31 m from its start
    assert np.linalg.norm(odom.odom_T_body[-1, :2, 3] - odom.odom_T_body[0, :2, 3]) == pytest.approx(31, abs=2)


def test_fused_track_beats_odometry_and_matches_the_fixes_it_never_saw(bag):
    fixes, _, odom = bag
    result = fuse_odometry_gps(odom, fixes)  # every 5th fix held out
    scores = result.holdout_scores()
    assert scores["held_out_fixes"] == 197 and scores["used_fixes"] == 792
    # GPS path about 396 m, start and end 13.4 m apart (the data set's description)
    gps = result.gps_enu
    assert np.sum(np.linalg.norm(np.diff(gps[:, :2], axis=0), axis=1)) == pytest.approx(396, abs=2)
    assert np.linalg.norm(gps[-1, :2] - gps[0, :2]) == pytest.approx(13.4, abs=1.0)
    assert scores["fused_rms_m"] <= 1.3 * scores["stated_drms_m"]
    assert scores["fused_rms_m"] <= 0.4 * scores["odometry_only_rms_m"]


def test_bad_topic_and_truncated_bag_are_named(tmp_path):
    with pytest.raises(InputError, match=r"no topic /gps.*/fix \(sensor_msgs/msg/NavSatFix\)"):
        read_navsatfix(BAG, "/gps")
    with pytest.raises(InputError, match="is nav_msgs/msg/Odometry, expected NavSatFix"):
        read_navsatfix(BAG, ODOM)
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(BAG.read_bytes()[:200_000])
    with pytest.raises(InputError, match="truncated.bag"):
        read_odometry(truncated, ODOM)
