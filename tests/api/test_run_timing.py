"""A run's wall time is the whole job's: reading the source (an image source's front-end, which
can be most of it) included."""

import dataclasses

from pancam_graph import api


def test_the_wall_time_counts_the_sources_reading(tmp_path):
    data = api.open_data("short_trail")
    assert data.load_s > 0.0  # open_data measured it
    slow = dataclasses.replace(data, load_s=30.0)  # as a front-end over images would take
    outcome = api.run("short_trail", out=tmp_path / "res", configs=("vo",), processes=1, figures=False,
                      opened=slow)
    assert outcome.result.wall_s >= 30.0
    assert outcome.result.wall_s < 30.0 + 120.0  # and the back-end's own time on top, not twice
