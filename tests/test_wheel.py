"""The built wheel, installed (not editable) into a fresh virtual environment, runs the commands:
a hand-kept package list once left `analysis/` out of the wheel and `analyze` failed outside an
editable install."""

import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]


def _run(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stdout + result.stderr
    return result


def test_wheel_in_a_fresh_venv_runs_analyze_and_a_scenario(tmp_path):
    _run(sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", tmp_path / "dist",
         REPO, cwd=tmp_path)
    wheel = next((tmp_path / "dist").glob("pancam_graph-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for package in ("analysis", "kinds", "sources", "solve", "store", "formats", "viz", "scenarios"):
        assert f"pancam_graph/{package}/__init__.py" in names, package
    assert "pancam_graph/scenarios/straight_500m.toml" in names

    venv = tmp_path / "venv"
    # without a pip of its own (ensurepip's 2.5 s): this environment's pip installs into it
    _run(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp_path)
    _run(sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install", "--quiet", "--no-deps", wheel,
         cwd=tmp_path)
    # The dependencies come from this environment's site-packages added as a plain path: its
    # .pth files (the editable install of this checkout among them) are not processed there.
    purelib = Path(_run(venv / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])",
                        cwd=tmp_path).stdout.strip())
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    where = _run(venv / "bin" / "python", "-c", "import pancam_graph; print(pancam_graph.__file__)", cwd=tmp_path)
    assert where.stdout.strip().startswith(str(venv)), where.stdout  # the wheel's copy, not this checkout

    cli = venv / "bin" / "pancam-graph"
    _run(cli, "analyze", "--rig", "mer_navcam", "--out", tmp_path / "analysis", cwd=tmp_path)
    assert (tmp_path / "analysis" / "table_3_2.md").stat().st_size > 100
    _run(cli, "run", "straight_500m", "--configs", "vo_sites", "--quiet", "--out", tmp_path / "run", cwd=tmp_path)
    assert (tmp_path / "run" / "metrics.json").stat().st_size > 100
    assert (tmp_path / "run" / "report.md").stat().st_size > 100
