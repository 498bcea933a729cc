"""The README's "Use from Python" example, run as written: the library call gives exactly the
metrics the CLI writes for the same run."""

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pancam_graph.cli import app

README = Path(__file__).parents[2] / "README.md"


def _example() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("**Use it from Python.**"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def _numbers(document: dict) -> dict:
    configs = document["configs"]
    return {name: {k: v for k, v in c.items() if k != "isam2_update_ms"} for name, c in configs.items()}


@pytest.mark.slow
def test_the_readme_example_runs_and_matches_the_cli(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(_example(), "README.md", "exec"), {"__name__": "__main__"})
    printed = capsys.readouterr().out
    library = json.loads((tmp_path / "results/short/metrics.json").read_text())
    assert re.search(r"vo_sites: ATE 0\.\d+ m, ANEES \d\.\d\d", printed)

    result = CliRunner().invoke(app, ["run", "short_trail", "--seed", "0", "--out", str(tmp_path / "cli"),
                                      "--quiet", "--no-plots"])
    assert result.exit_code == 0, result.output
    cli = json.loads((tmp_path / "cli/metrics.json").read_text())
    assert library["schema"] == cli["schema"] == 2
    assert _numbers(library) == _numbers(cli)
    ate = library["configs"]["vo_sites"]["ate_rmse_m"]
    assert f"vo_sites: ATE {ate:.3f} m" in printed


@pytest.mark.slow
def test_the_readme_example_with_a_bigger_scenario_runs_as_a_script(tmp_path):
    """A user swaps in denver_trail (run on both cores, worker processes importing the script
    again) and runs the example as a file: it runs, and leaves its results only."""
    import subprocess
    import sys

    script = tmp_path / "example.py"
    script.write_text(_example().replace('"short_trail"', '"denver_trail"').replace("results/short", "results/denver"))
    ran = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert ran.returncode == 0, ran.stderr[-2000:]
    assert "vo_sites: ATE" in ran.stdout and (tmp_path / "results/denver/metrics.json").is_file()
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == ["denver"]
