"""A process's memory: its peak and proportional set size, the garbage collector set aside, and
freed memory handed back to the system."""

from __future__ import annotations

import ctypes
import gc
import os
import resource

from .processes import release_mapped_pages

_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20 if hasattr(os, "sysconf") else 0.0


def peak_rss_mb() -> float:
    """This process's peak resident memory so far."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb(pid: int | None = None) -> float | None:
    """The resident memory now of process `pid` (default: this one); None where the kernel does
    not say (not Linux) or the process has gone."""
    try:
        with open(f"/proc/{pid or 'self'}/statm") as f:
            return int(f.read().split()[1]) * _PAGE_MB
    except (OSError, ValueError, IndexError):
        return None


def settle_garbage_collector() -> None:
    """Collect, then set aside every object that survived from Python's garbage collector
    (`gc.freeze`), which otherwise walks all of them at each of its full collections: the
    traverse's stops and everything the run built so far. Without this the collections came
    at random stops and grew with the traverse.
    Called at checkpoints, so each collection walks what a few stops made; `gc.unfreeze` at
    the end of the run hands the rest back."""
    gc.collect()
    gc.freeze()


def release_memory(collect_cycles: bool = True) -> None:
    """Hand the memory of what was freed back to the system: glibc keeps it otherwise, and the
    process's footprint stays where its largest graph left it. The pages of arrays read back
    from a process apart go back to the page cache too (processes.release_mapped_pages).
    `collect_cycles`: a full garbage collection first, for what only it frees (it walks every
    object of the process: 0.1-0.25 s after a short run); False where the caller broke its
    cycles itself (Localizer.close)."""
    release_mapped_pages()
    if collect_cycles:
        gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def pss_mb() -> float | None:
    """This process's proportional set size now (Linux): its resident memory with each page
    shared with other processes (the fork server's imports) counted as its share; None where
    the kernel does not say."""
    try:
        with open("/proc/self/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None
