"""The VO error model as a named preset (issue 33): `vo_error_model = "real_images"` sets the
model measured on real images (docs/frontend.md) from a scenario file, an observation folder's
manifest or `run --vo-error-model`, without copying its numbers; show-config and run.toml show
what it set, and reproduce.sh carries the flag."""

import json
import tomllib

import pytest
from typer.testing import CliRunner

from pancam_graph.cli import app
from pancam_graph.config import (
    DEFAULT_CONFIGURATIONS,
    EstimatorConfig,
    bundled_scenarios,
    load_scenario,
    with_vo_error_model,
)
from pancam_graph.errors import ConfigError
from pancam_graph.store.observation_folder import read_observations

runner = CliRunner()
REAL = {"vo_max_range_m": 40.0, "vo_translation_floor": 0.005, "vo_rotation_floor_deg_per_m": 0.03,
        "direction_sigma": 0.005}


def _values(estimator) -> dict:
    """What the preset sets: the estimator's keys and the shared VO direction bias (its vo_scale section)."""
    values = estimator if isinstance(estimator, dict) else estimator.model_dump()
    return {key: values["vo_scale"][key] if key == "direction_sigma" else values[key] for key in REAL}


def test_the_preset_sets_the_measured_model_and_overrules_and_undoes_its_own_keys():
    real = EstimatorConfig(vo_error_model="real_images", vo_translation_floor=0.5,
                           vo_scale={"direction_sigma": 0.05, "sigma": 0.02})
    # the preset's keys are its own (a file's values go with pixel_noise); the section's other keys stay
    assert _values(real) == REAL and real.vo_scale.sigma == 0.02
    assert real.configurations["full"] == ["vo", "sites", "hrc", "gps", "vo_scale"]
    assert real.configurations["dead_reckoning"] == DEFAULT_CONFIGURATIONS["dead_reckoning"]  # no VO, no scale
    assert EstimatorConfig.model_validate(real.model_dump(mode="json")) == real  # run.toml reads back the same
    back = with_vo_error_model(real, "pixel_noise")
    assert back == EstimatorConfig(vo_scale={"sigma": 0.02}) and back.vo_translation_floor == 0.0
    assert back.vo_scale.direction_sigma == 0.0
    dumped = EstimatorConfig.model_validate(EstimatorConfig().model_dump(mode="json"))  # every key set, as files are
    assert with_vo_error_model(dumped, "real_images") == EstimatorConfig(vo_error_model="real_images")
    with pytest.raises(ConfigError, match="vo_error_model 'kitti': expected pixel_noise or real_images"):
        with_vo_error_model(real, "kitti")


def test_a_scenario_names_the_preset_and_show_config_prints_what_it_set(tmp_path):
    path = tmp_path / "real.toml"
    # the ideal simulator: under the realistic profile the estimated calibration builds the VO's
    # factors in place of the preset's vo_scale (tests/kinds/test_stereo_calibration.py)
    ideal = bundled_scenarios()["short_trail"].read_text().replace('profile = "realistic"', 'profile = "ideal"')
    path.write_text(ideal + '\n[estimator]\nvo_error_model = "real_images"\n')
    assert _values(load_scenario(path).estimator) == REAL
    result = runner.invoke(app, ["show-config", str(path)])
    assert result.exit_code == 0, result.output
    shown = tomllib.loads(result.output)["estimator"]
    assert shown["vo_error_model"] == "real_images" and _values(shown) == REAL
    assert shown["configurations"]["vo"] == ["vo", "vo_scale"]


@pytest.mark.slow
def test_a_manifest_names_the_preset_and_the_command_line_overrules_it(tmp_path):
    folder = tmp_path / "observations"
    # the ideal simulator's white pixel noise, which the pixel_noise model states exactly
    assert runner.invoke(app, ["simulate", "short_trail", "--out", str(folder), "--errors", "ideal"]).exit_code == 0
    manifest = folder / "traverse.toml"
    text = manifest.read_text()
    assert 'vo_error_model = "pixel_noise"' in text  # simulate writes the whole estimator
    manifest.write_text(text.replace('vo_error_model = "pixel_noise"', 'vo_error_model = "real_images"'))
    assert _values(read_observations(folder).estimator) == REAL

    runs = {}
    for name, flags in (("manifest", []), ("cli", ["--vo-error-model", "pixel_noise"])):
        out = tmp_path / name
        result = runner.invoke(app, ["run", str(folder), "--configs", "vo", "--out", str(out), "--quiet", *flags])
        assert result.exit_code == 0, result.output
        runs[name] = json.loads((out / "metrics.json").read_text())["configs"]["vo"]
        estimator = tomllib.loads((out / "run.toml").read_text())["estimator"]
        assert estimator["vo_error_model"] == ("real_images" if name == "manifest" else "pixel_noise")
    assert "--vo-error-model pixel_noise" in (tmp_path / "cli" / "reproduce.sh").read_text()
    # Same estimate (a VO chain alone is the composed steps); the real-image floors widen its
    # covariance several times over on simulated pixels, where white noise is the truth.
    assert runs["manifest"]["ate_rmse_m"] == pytest.approx(runs["cli"]["ate_rmse_m"], rel=1e-9)
    assert runs["manifest"]["anees"] < runs["cli"]["anees"] / 3


@pytest.mark.slow
def test_the_command_line_sets_the_preset_on_a_scenario_and_its_scenario_toml_keeps_it(tmp_path):
    out = tmp_path / "run"
    result = runner.invoke(app, ["run", "short_trail", "--configs", "vo", "--vo-error-model", "real_images",
                                 "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    saved = load_scenario(out / "scenario.toml").estimator  # what reproduce.sh runs
    assert saved.vo_error_model == "real_images" and _values(saved) == REAL
    assert tomllib.loads((out / "run.toml").read_text())["estimator"]["vo_translation_floor"] == 0.005
