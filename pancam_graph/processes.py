"""Where the run's worker processes come from: forked from a server that imported GTSAM, OpenCV
and this package once and did nothing else. No fork of a process that has run OpenCV (its
threads), and no fresh interpreter per worker (each spent 1.5 s of a core importing). Spawned
where there is no fork server (Windows)."""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
import os
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


def start_process_server() -> None:
    """Start the fork server now: it imports while the run loads its source."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        process_context()
        forkserver.ensure_running()
