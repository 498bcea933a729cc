"""A run's wall time is the whole job's: reading the source (an image source's front-end, which
can be most of it) included, once."""

import dataclasses

from pancam_graph import api


def test_the_wall_time_counts_the_sources_reading_once(tmp_path):
    data = api.open_data("short_trail")
    assert data.load_s > 0.0  # open_data measured it
    walls = []
    for load_s in (30.0, 90.0):  # as a front-end over images would take
        outcome = api.run("short_trail", out=tmp_path / f"res{load_s:.0f}", configs=("vo",), processes=1,
                          figures=False, opened=dataclasses.replace(data, load_s=load_s))
        assert outcome.result.wall_s >= load_s
        walls.append(outcome.result.wall_s)
    # 60 s more reading is 60 s more wall, not 120 (counted twice) or 0: the back-end's own few
    # seconds differ between the two runs by far less than the 60 s either mistake would add
    assert abs((walls[1] - walls[0]) - 60.0) < 30.0
