"""Where the run's worker processes come from: forked from a server that imported GTSAM, OpenCV
and this package once and did nothing else. No fork of a process that has run OpenCV (its
threads), and no fresh interpreter per worker (each would pay the imports again). Spawned
where there is no fork server (Windows)."""

from __future__ import annotations

import ast
import ctypes
import mmap
import multiprocessing
import multiprocessing.context
import os
import pickle
import platform
import threading
import time
import weakref
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing import forkserver
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..errors import ProcessDied
from .scratch import temporary_folder

T = TypeVar("T")

# everything a worker runs, then what hands back the pages the imports read (fork_server)
PRELOAD = ["pancam_graph.solve.side_by_side", "pancam_graph.runtime.fork_server"]


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
    updates and numpy free such blocks all the time, and the process tree held more for it
    (docs/performance.md). Elsewhere than glibc, nothing."""
    if not _glibc():
        return
    libc = ctypes.CDLL("libc.so.6")
    libc.mallopt(M_TRIM_THRESHOLD, MALLOC_THRESHOLD_BYTES)
    libc.mallopt(M_MMAP_THRESHOLD, MALLOC_THRESHOLD_BYTES)


IMAGE_WORK_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's own ceiling for its adaptive mmap threshold


@contextmanager
def heap_for_image_work() -> Iterator[None]:
    """Blocks up to 32 MB from the heap while images are worked on (the image front-end,
    rendering), then the held thresholds again and the heap's free memory handed back
    (malloc_trim). Images, and OpenCV's and numpy's buffers around them, come and go thousands
    of times; at the held 128 kB threshold each is mapped afresh and every page of it faulted in
    and zeroed by the kernel (docs/performance.md: a run from rendered short_trail images spent
    28 of its 45 s in the kernel). Elsewhere than glibc, nothing."""
    global _image_work_depth
    if not _glibc():
        yield
        return
    libc = ctypes.CDLL("libc.so.6")
    if _image_work_depth == 0:
        libc.mallopt(M_MMAP_THRESHOLD, IMAGE_WORK_THRESHOLD_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, 2 * IMAGE_WORK_THRESHOLD_BYTES)
    _image_work_depth += 1
    try:
        yield
    finally:
        _image_work_depth -= 1
        if _image_work_depth == 0:  # the outermost image work is done (the front-end nests them)
            hold_malloc_thresholds()
            libc.malloc_trim(0)


_image_work_depth = 0


WATCH_EVERY_S = 0.2  # how often a worker looks for the run's process


def watch_the_run(run_pid: int, also: Callable[[], bool] = lambda: False) -> None:
    """In a worker: exit at once when the run's process is gone, whatever killed it (SIGKILL
    too, which runs no clean-up), or when `also()` says so. A worker waiting for work holds its
    own end of the pool's pipe open, and a busy one reads no pipe: neither would notice."""

    def watch() -> None:
        while True:
            time.sleep(WATCH_EVERY_S)
            if also():
                os._exit(1)
            try:
                os.kill(run_pid, 0)
            except ProcessLookupError:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="watch-the-run").start()


def start_worker(run_pid: int) -> None:
    """A pool worker's start: glibc's malloc thresholds held, and the run watched."""
    hold_malloc_thresholds()
    watch_the_run(run_pid)


def unguarded_script_call() -> str | None:
    """`file:line` where the script run as the main module calls into this package at its top
    level outside `if __name__ == "__main__":`, or None. Worker processes import the main module
    again (the fork server, or spawn, does, to find what they run): such a call would run again
    in them and break the pool with a traceback from deep inside multiprocessing."""
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    frame = sys._getframe(1)
    while frame is not None and not (frame.f_code.co_name == "<module>"
                                     and frame.f_globals.get("__name__") == "__main__"):
        frame = frame.f_back
    if frame is None or path is None or frame.f_code.co_filename != path:
        return None
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None
    for node in tree.body:
        if isinstance(node, ast.If) and _tests_main(node.test) and node.lineno <= frame.f_lineno <= node.end_lineno:
            return None
    return f"{path}:{frame.f_lineno}"


def _tests_main(test) -> bool:
    """`__name__ == "__main__"`, either way round."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = [test.left, *test.comparators]
    return (any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides)
            and any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides))


def start_process_server() -> None:
    """Start the fork server now: it imports while the run loads its source."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        process_context()
        forkserver.ensure_running()


def call_apart(function: Callable[..., T], *args) -> T:
    """`function(*args)` in a process of its own, forked from the fork server, which exits when
    it is done. What the call imported and the scraps of its allocations go with that process (a
    scenario's simulation imports pvlib and pandas for its sun; docs/performance.md measures the
    run process with and without). Its errors are raised here as they were there.

    The result comes back through files: its objects pickled, and the contents of its arrays
    written apart, each at an aligned offset of one file that this process maps read-only. Its
    arrays are views of that file (read-only): their pages are resident only while they are
    read, and `release_mapped_pages` hands them back to the page cache."""
    with temporary_folder("apart") as folder:
        folder = Path(folder)
        with ProcessPoolExecutor(1, mp_context=process_context(), initializer=start_worker,
                                 initargs=(os.getpid(),)) as pool:
            try:
                pool.submit(_call_into, folder, function, args).result()
            except BrokenProcessPool as exc:
                raise ProcessDied(f"the process running {function.__name__} stopped unexpectedly (killed, or "
                                       f"out of memory?): {exc}") from None
        with open(folder / _OBJECTS, "rb") as f:
            spans = pickle.load(f)
            return pickle.load(f, buffers=_mapped_spans(folder / _ARRAYS, spans))


_OBJECTS, _ARRAYS = "objects.pickle", "arrays.bin"
ARRAY_ALIGNMENT = 64  # bytes: at least what numpy's own allocations get from malloc (16)
_mappings: weakref.WeakSet[mmap.mmap] = weakref.WeakSet()


def _glibc() -> bool:
    return platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


# Reading mapped arrays in order maps in the pages around them too (the kernel's fault-around), and
# they stay resident: released every so often, they do not pile up along a long traverse
# (docs/performance.md).
RELEASE_EVERY_STOPS = 2048


def map_npy(path: Path) -> np.ndarray:
    """An .npy file's array, mapped read-only; `release_mapped_pages` releases its pages too."""
    array = np.load(path, mmap_mode="r")
    mapping = getattr(array, "_mmap", None)  # numpy's memmap keeps its mmap there
    if isinstance(mapping, mmap.mmap):
        _mappings.add(mapping)
    return np.asarray(array)  # a view: the mapping lives while it does


def release_mapped_pages() -> None:
    """Hand the pages of mapped arrays (results read back from a process apart, `call_apart`;
    files read with `map_npy`) to the page cache: the arrays stay as they are, and a page read
    again comes back from the file."""
    for mapping in list(_mappings):
        if not mapping.closed and hasattr(mmap, "MADV_DONTNEED"):
            mapping.madvise(mmap.MADV_DONTNEED)


MADV_DONTNEED = 4  # Linux's


def release_library_pages() -> int:
    """Drop from this process's page tables the resident pages of the files it maps read-only
    and never wrote to (the shared libraries' code and constants, the modules' compiled code):
    a page used again comes back from the page cache, as it is. For a process done with most of
    the code it ran: the fork server after its imports, the run's process while it waits for its
    groups. Those pages count in every process's resident memory (docs/performance.md: tens of MB
    a process). Returns the kB released (0 where not Linux with glibc)."""
    if not _glibc():
        return 0
    try:
        with open("/proc/self/smaps") as f:
            mappings = _clean_file_mappings(f)
    except OSError:
        return 0
    madvise = ctypes.CDLL("libc.so.6").madvise
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    released = 0
    for start, end, rss_kb in mappings:
        if madvise(start, end - start, MADV_DONTNEED) == 0:
            released += rss_kb
    return released


def _clean_file_mappings(smaps: Iterable[str]) -> list[tuple[int, int, int]]:
    """(start, end, resident kB) of the private, read-only mappings of files with no page of
    their own (`Anonymous: 0 kB`): their pages are the file's, so dropping them loses nothing."""
    mappings: list[dict] = []  # each: its range, whether a read-only private file, its kB
    for line in smaps:
        fields = line.split()
        if len(fields) >= 5 and "-" in fields[0] and len(fields[1]) == 4:  # a mapping's header
            start, end = (int(x, 16) for x in fields[0].split("-"))
            path = fields[5] if len(fields) >= 6 else ""
            file = fields[1][1] == "-" and fields[1][3] == "p" and path.startswith("/") and fields[4] != "0"
            mappings.append({"start": start, "end": end, "file": file, "Rss:": 0, "Anonymous:": 0})
        elif mappings and fields[:1] in (["Rss:"], ["Anonymous:"]):
            mappings[-1][fields[0]] = int(fields[1])
    # a page written to (copied on write) is not the file's any more
    return [(m["start"], m["end"], m["Rss:"]) for m in mappings if m["file"] and m["Rss:"] and not m["Anonymous:"]]


def _call_into(folder: Path, function: Callable, args: tuple) -> None:
    result = function(*args)
    spans: list[tuple[int, int]] = []
    with open(folder / _ARRAYS, "wb") as arrays:
        def write_apart(buffer: pickle.PickleBuffer) -> bool:
            data = buffer.raw()
            arrays.write(bytes(-arrays.tell() % ARRAY_ALIGNMENT))
            spans.append((arrays.tell(), data.nbytes))
            arrays.write(data)
            return False  # out of band: not in the pickle

        objects = pickle.dumps(result, protocol=5, buffer_callback=write_apart)
    with open(folder / _OBJECTS, "wb") as f:
        pickle.dump(spans, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.write(objects)


def _mapped_spans(path: Path, spans: list[tuple[int, int]]) -> list[memoryview]:
    if not spans or path.stat().st_size == 0:
        return [memoryview(b"")] * len(spans)
    with open(path, "rb") as f:
        mapping = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # outlives the file's name
    _mappings.add(mapping)
    whole = memoryview(mapping)
    return [whole[start:start + size] for start, size in spans]
