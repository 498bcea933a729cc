"""Where the run's worker processes come from: forked from a server that imported GTSAM, OpenCV
and this package once and did nothing else. No fork of a process that has run OpenCV (its
threads), and no fresh interpreter per worker (each spent 1.5 s of a core importing). Spawned
where there is no fork server (Windows)."""

from __future__ import annotations

import ctypes
import multiprocessing
import multiprocessing.context
import os
import platform
from multiprocessing import forkserver

PRELOAD = ["pancam_graph.solve.side_by_side"]  # imports everything a worker runs


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def process_context() -> multiprocessing.context.BaseContext:
    """The context to make worker processes with."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    return context


# glibc's mallopt parameters, and its default for both, held fixed
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MALLOC_THRESHOLD_BYTES = 128 * 1024


def hold_malloc_thresholds() -> None:
    """Keep glibc's malloc at its default thresholds in this process (and the ones it forks).
    By default glibc raises its mmap threshold to the largest mapped block freed so far (up to
    32 MB) and its trim threshold to twice that; after that, blocks up to that size come from
    the heap, and the heap's free space goes back to the system only from its top. iSAM2's
    updates and numpy free such blocks all the time: long_traverse's process tree held 60 MB
    more (summed RSS 1,211 against 1,148-1,153 MB, the same wall). Elsewhere than glibc,
    nothing."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return
    libc = ctypes.CDLL("libc.so.6")
    libc.mallopt(M_TRIM_THRESHOLD, MALLOC_THRESHOLD_BYTES)
    libc.mallopt(M_MMAP_THRESHOLD, MALLOC_THRESHOLD_BYTES)


def start_process_server() -> None:
    """Start the fork server now: it imports while the run loads its source."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        process_context()
        forkserver.ensure_running()
