"""The shared scalars' keys come from one allocator (graph.keys.shared): every kind's block is
its own, the same in every process, and each kind's variables fall in its block."""

import subprocess
import sys

import gtsam
import pytest

import pancam_graph.kinds  # noqa: F401  (every kind takes its block when imported)
from pancam_graph.graph import keys
from pancam_graph.kinds.orbital import MAX_MAPS, bias_keys
from pancam_graph.kinds.vo_scale import VO_LATERAL, VO_SCALE, VO_VERTICAL
from pancam_graph.kinds.wheel_slip import SLIP


def _indices(*keys_):
    return {gtsam.Symbol(k).index() for k in keys_}


def test_no_two_kinds_share_a_key_and_each_kind_uses_its_own_block():
    blocks = keys.shared_blocks()
    assert {"wheel_slip", "vo_scale", "orbital"} <= blocks.keys()
    taken = [k for block in blocks.values() for k in block]
    assert len(taken) == len(set(taken))  # disjoint
    assert _indices(SLIP) <= set(blocks["wheel_slip"])
    assert _indices(VO_SCALE, VO_LATERAL, VO_VERTICAL) <= set(blocks["vo_scale"])
    every_bias = {k for m in range(MAX_MAPS) for k in _indices(*bias_keys(m))}
    assert every_bias == set(blocks["orbital"]) and len(every_bias) == 4 * MAX_MAPS
    assert all(gtsam.Symbol(k).chr() == ord("s") for k in (SLIP, VO_SCALE, *bias_keys(0)))


def test_asking_again_gives_the_same_block_and_another_size_is_refused():
    assert keys.shared("vo_scale", 3) == (VO_SCALE, VO_LATERAL, VO_VERTICAL)
    with pytest.raises(ValueError, match="vo_scale already holds 3 shared scalars, not 2"):
        keys.shared("vo_scale", 2)
    with pytest.raises(ValueError, match="at least one"):
        keys.shared("nobody", 0)


def test_a_worker_process_numbers_the_blocks_alike():
    """A process that imports one kind module first gets the same blocks (kinds/__init__ imports
    every kind in one order): pickled graphs mean the same variables in every process."""
    code = ("import pancam_graph.kinds.wheel_slip as w\nfrom pancam_graph.graph import keys\n"
            "print(sorted((n, b.start, b.stop) for n, b in keys.shared_blocks().items()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(sorted((n, b.start, b.stop) for n, b in keys.shared_blocks().items()))
