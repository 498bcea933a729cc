"""Where the run's processes come from: a call in a process of its own, and the allocator's
thresholds held in every process of a run."""

import platform
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.errors import ConfigError
from pancam_graph.runtime import processes
from pancam_graph.runtime.processes import call_apart, release_mapped_pages
from pancam_graph.solve.pipeline import RunOptions, run, simulated, worth_simulating_apart
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
    here = run(*simulated(scenario, 1)[:2], scenario.estimator, 1, RunOptions(configs=("vo_sites", "full")))
    traverse, truth, _, _ = call_apart(simulated, scenario, 1)
    assert not traverse.stops[5].stereo.uvv.flags.writeable
    release_mapped_pages()  # the arrays stay what they were
    apart = run(traverse, truth, scenario.estimator, 1, RunOptions(configs=("vo_sites", "full")))
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


GLIBC = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc")

# What each malloc script below starts with: glibc's malloc and free, and the resident MB.
_LIBC = """
import contextlib, ctypes, resource, sys
from pancam_graph.runtime.processes import heap_for_image_work, hold_malloc_thresholds
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
"""


def _in_a_fresh_interpreter(script: str, mode: str) -> list[str]:
    """What `script` (after _LIBC) prints, run with sys.argv[1] = `mode`, split in words."""
    out = subprocess.run([sys.executable, "-c", _LIBC + script, mode], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).parent)
    return out.stdout.split()


# 1 MB blocks, each followed by a 64 KB one that stays, after an 8 MB block was freed (glibc's
# dynamic threshold then serves 1 MB blocks from the heap); the MB of them still resident once
# every 1 MB block is freed.
_KEPT_AFTER_FREEING = """
if sys.argv[1] == "held":
    hold_malloc_thresholds()
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


@GLIBC
def test_freed_blocks_go_back_with_the_thresholds_held():
    def kept_mb(mode: str) -> float:
        return float(_in_a_fresh_interpreter(_KEPT_AFTER_FREEING, mode)[0])

    assert kept_mb("dynamic") > 150.0  # glibc's default behaviour: the 200 MB stay resident
    assert kept_mb("held") < 10.0


# With the thresholds held: 200 times a 1 MB block written and freed, a 64 KB one kept beside
# each, inside heap_for_image_work or not; the page faults that took, and the MB still resident
# after the context (or the loop) ends.
_FAULTS_AND_KEPT = """
hold_malloc_thresholds()
before = rss_mb()
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
small = []
with heap_for_image_work() if sys.argv[1] == "images" else contextlib.nullcontext():
    for _ in range(200):
        block = libc.malloc(1 << 20)
        ctypes.memset(block, 1, 1 << 20)
        small.append(libc.malloc(64 << 10))
        libc.free(block)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
print(faults, rss_mb() - before)
"""


@GLIBC
def test_image_work_reuses_the_heap_and_hands_it_back_after():
    def faults_and_kept(mode: str) -> tuple[int, float]:
        faults, kept = _in_a_fresh_interpreter(_FAULTS_AND_KEPT, mode)
        return int(faults), float(kept)

    held_faults, _ = faults_and_kept("held")
    image_faults, image_kept = faults_and_kept("images")
    assert held_faults > 200 * 256 * 0.9  # every 4 kB page of every 1 MB block faulted in afresh
    assert image_faults < held_faults / 10  # the heap's pages reused
    assert image_kept < 20.0  # the 64 KB blocks (13 MB) and little more


_SMAPS = """\
7f0000000000-7f0000010000 r-xp 00000000 08:01 1234 /lib/libcode.so
Rss:                  40 kB
Anonymous:             0 kB
7f0000010000-7f0000012000 r--p 00010000 08:01 1234 /lib/libcode.so
Rss:                   8 kB
Anonymous:             4 kB
7f0000012000-7f0000013000 rw-p 00012000 08:01 1234 /lib/libcode.so
Rss:                   4 kB
Anonymous:             0 kB
7f0000020000-7f0000030000 r--p 00000000 08:01 99 /lib/unread.so
Rss:                   0 kB
Anonymous:             0 kB
7f0000040000-7f0000050000 rw-p 00000000 00:00 0
Rss:                  64 kB
Anonymous:            64 kB
7f0000060000-7f0000061000 r--s 00000000 00:05 7 /dev/shm/shared
Rss:                   4 kB
Anonymous:             0 kB
7ffd00000000-7ffd00002000 r-xp 00000000 00:00 0                          [vdso]
Rss:                   8 kB
Anonymous:             0 kB
7f0000070000-7f0000078000 r--p 00000000 08:01 55 /lib/constants.so
Rss:                  12 kB
Anonymous:             0 kB
VmFlags: rd mr mw me sd
"""


def test_only_read_only_unwritten_file_pages_are_released():
    # the code and constants of a file, not what was written (a relocated page, data), shared or
    # anonymous memory, nor the kernel's vdso
    assert processes._clean_file_mappings(_SMAPS.splitlines()) == [
        (0x7f0000000000, 0x7f0000010000, 40), (0x7f0000070000, 0x7f0000078000, 12)]


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="Linux's smaps")
def test_a_process_runs_on_after_its_library_pages_are_released():
    script = ("import numpy as np, gtsam\n"
              "from pancam_graph.runtime import processes\n"
              "def file_kb():\n"
              "    return int(next(l for l in open('/proc/self/status') if l.startswith('RssFile')).split()[1])\n"
              "before = file_kb(); released = processes.release_library_pages(); after = file_kb()\n"
              "x = gtsam.Pose3(gtsam.Rot3.Yaw(0.5), [1.0, 2.0, 3.0]).inverse().translation()\n"
              "print(before, released, after, *np.linalg.solve(np.eye(3) * 2.0, x))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    before, released, after, *x = (float(v) for v in out.stdout.split())
    assert released > 10_000 and after < before - 10_000  # kB: the imports' code pages, gone from the process
    expected = -(gtsam.Rot3.Yaw(0.5).inverse().matrix() @ [1.0, 2.0, 3.0]) / 2.0
    np.testing.assert_allclose(x, expected, rtol=1e-12)
