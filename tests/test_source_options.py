"""Source options: each one's flag, help and check written once, the CLI's flags made from them."""

import pytest
from typer.testing import CliRunner

from pancam_graph.cli import app
from pancam_graph.config import SourceOptions
from pancam_graph.errors import ConfigError


def test_stereo_topics_given_as_text_become_a_pair():
    assert SourceOptions(stereo_topics="/l/image, /r/image").stereo_topics == ("/l/image", "/r/image")
    assert SourceOptions(stereo_topics=("/l", "/r")).stereo_topics == ("/l", "/r")


@pytest.mark.parametrize("given,words", [
    ({"detector": "surf"}, "--detector 'surf'"),
    ({"stereo_topics": "/only_one"}, "--stereo-topics '/only_one'"),
    ({"seed": -1}, "--seed -1: must be at least 0"),
    ({"holdout_every": -5}, "--holdout-every -5"),
])
def test_a_bad_option_is_refused_naming_its_flag(given, words):
    with pytest.raises(ConfigError, match=words):
        SourceOptions(**given)


def test_given_and_check_name_the_flag():
    options = SourceOptions(gps_topic="/fix", skip_bad_frames=True)
    assert options.given() == {"gps_topic": "/fix", "skip_bad_frames": True}
    with pytest.raises(ConfigError, match="--gps-topic does not apply to a scenario source"):
        options.check("scenario", {"skip_bad_frames"})


def test_run_takes_every_source_option_as_its_declared_flag():
    result = CliRunner().invoke(app, ["run", "--help"], terminal_width=200)
    assert result.exit_code == 0
    for name, flag in SourceOptions.flags().items():
        assert flag in result.output, flag
        assert SourceOptions.help(name)[:30] in result.output
    track = CliRunner().invoke(app, ["track", "--help"], terminal_width=200).output
    assert "--detector" in track and "--skip-bad-frames" in track and "--gps-topic" not in track


def test_a_zero_on_the_command_line_is_given(monkeypatch):
    """--holdout-every 0 (use every fix) must reach the source, not read as "not given"."""
    from pancam_graph import api

    seen = {}

    def open_data(source, options, out, progress, **_):
        seen["options"] = options
        raise ConfigError("stop here")

    monkeypatch.setattr(api, "open_data", open_data)
    result = CliRunner().invoke(app, ["run", "x.bag", "--holdout-every", "0", "--one-process"])
    assert result.exit_code == 2
    assert seen["options"].given() == {"holdout_every": 0}
