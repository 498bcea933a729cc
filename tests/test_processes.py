"""Where the run's processes come from: a call in a process of its own, and the allocator's
thresholds held in every process of a run."""

import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError
from pancam_graph.processes import call_apart, release_mapped_pages
from pancam_graph.solve.pipeline import RunOptions, run_traverse, simulated, worth_simulating_apart
from pancam_graph.sources import source_for


def test_a_simulation_apart_is_the_one_simulated_here():
    scenario = load_scenario(resolve_scenario("short_trail"))
    here, _, _, _ = simulated(scenario, 3)
    apart, truth, resolved, info = call_apart(simulated, scenario, 3)
    assert resolved.seed == 3 and info.kind == "scenario"
    assert len(apart.stops) == len(here.stops)
    for a, b in zip(apart.stops, here.stops, strict=True):
        assert np.array_equal(a.stereo.track_ids, b.stereo.track_ids)
        assert np.array_equal(a.stereo.uvv, b.stereo.uvv)
        assert len(a.panorama) == len(b.panorama)
    assert truth.world_T_body.shape == (len(here.stops), 4, 4)


def test_a_run_on_data_read_back_is_the_run_on_data_simulated_here():
    """Every array read back from a process apart is a read-only view of a mapped file: a run
    that wrote into its inputs would fail here, and one whose numbers depended on where its
    arrays live would differ."""
    scenario = load_scenario(resolve_scenario("short_trail"))
    here = run_traverse(*simulated(scenario, 1)[:2], scenario.estimator, 1, RunOptions(configs=("vo_sites", "full")))
    traverse, truth, _, _ = call_apart(simulated, scenario, 1)
    assert not traverse.stops[5].stereo.uvv.flags.writeable
    release_mapped_pages()  # the arrays stay what they were
    apart = run_traverse(traverse, truth, scenario.estimator, 1, RunOptions(configs=("vo_sites", "full")))
    for name in ("vo_sites", "full"):
        assert np.array_equal(apart.configurations[name].world_T_body, here.configurations[name].world_T_body)
        assert np.array_equal(apart.configurations[name].position_covariance,
                              here.configurations[name].position_covariance)


def test_an_error_apart_is_raised_here_as_it_was_there(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\nseed = "zero"\n', encoding="utf-8")
    with pytest.raises(ConfigError) as here:
        load_scenario(bad)
    with pytest.raises(ConfigError) as apart:
        call_apart(load_scenario, bad)
    assert str(apart.value) == str(here.value)


def test_only_a_long_scenario_is_simulated_apart():
    assert not worth_simulating_apart(load_scenario(resolve_scenario("denver_trail")))  # 0.9 km
    assert worth_simulating_apart(load_scenario(resolve_scenario("long_traverse")))  # 10.4 km
    scenario = source_for("long_traverse")
    assert scenario.apart("long_traverse") and not scenario.apart("denver_trail")


# In a fresh interpreter: 1 MB blocks, each followed by a 64 KB one that stays, after an 8 MB
# block was freed (glibc's dynamic threshold then serves 1 MB blocks from the heap); the MB of
# them still resident once every 1 MB block is freed.
_KEPT_AFTER_FREEING = """
import ctypes, sys
from pancam_graph.processes import hold_malloc_thresholds
if sys.argv[1] == "held":
    hold_malloc_thresholds()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

big = libc.malloc(8 << 20)
ctypes.memset(big, 1, 8 << 20)
libc.free(big)
before = rss_mb()
blocks, small = [], []
for _ in range(200):
    blocks.append(libc.malloc(1 << 20))
    ctypes.memset(blocks[-1], 1, 1 << 20)
    small.append(libc.malloc(64 << 10))
for block in blocks:
    libc.free(block)
print(rss_mb() - before)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc")
def test_freed_blocks_go_back_with_the_thresholds_held():
    def kept_mb(mode: str) -> float:
        out = subprocess.run([sys.executable, "-c", _KEPT_AFTER_FREEING, mode], capture_output=True, text=True,
                             check=True, cwd=Path(__file__).parent)
        return float(out.stdout)

    assert kept_mb("dynamic") > 150.0  # glibc's default behaviour: the 200 MB stay resident
    assert kept_mb("held") < 10.0
