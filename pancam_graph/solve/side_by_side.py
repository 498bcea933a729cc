"""Groups of configurations side by side, one worker process each.

The configurations of a run share the traverse and its motions and nothing else. Each worker
runs a group over the whole traverse, saves its own checkpoints and evaluates its
configurations. The pool has one worker per core and no more: the group without VO and the
stereo VO's blocks of stops first, then the groups with VO on the motions. Not more processes
than cores: iSAM2 lives in the caches, and each switch to another process empties them
(docs/performance.md measures what that cost).

A group's estimate is the one it would get in a single process: the same motions in the same
order, the same updates (group.localize_group is the loop either way).
"""

from __future__ import annotations

import os
import pickle
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import GraphError
from ..frontend.motion import Motions, VoMotions, dead_reckoning_motion, motion_from
from ..frontend.vo_ahead import BLOCK_STOPS, VoAhead
from ..kinds import stop_records, uses_vo
from ..records import Traverse
from ..runtime.atomic import writing
from ..runtime.memory import release_memory, rss_mb
from ..runtime.processes import (
    RELEASE_EVERY_STOPS,
    hold_malloc_thresholds,
    map_npy,
    process_context,
    release_library_pages,
    release_mapped_pages,
    watch_the_run,
)
from ..runtime.scratch import temporary_folder
from .group import GroupJob, GroupOutcome, ProgressCallback, localize_group, new_state
from .state import Checkpoints, RunState
from .stop_records import StopRecords

_stops_done = None  # in a worker: the shared count of stops each group has stepped, then "stop now"
_run_pid = 0  # in a worker: the process it works for


def localize_side_by_side(job: GroupJob, groups: list[dict[str, list[str]]], resume: list[RunState] | None,
                     known: VoMotions | None, save: Checkpoints | None, progress: ProgressCallback | None,
                     start: float, memory: MemoryWatch) -> list[GroupOutcome]:
    """Each group of configurations in a worker of a pool of `job.options.processes` (its
    state from `resume` when it has one): the groups without VO at once, the stereo VO in
    blocks beside them, then the groups with VO; their outcomes in the order of `groups`.
    `memory` watches the run's processes meanwhile."""
    n = len(job.traverse.stops)
    context = process_context()
    done = context.Array("l", len(groups) + 1, lock=False)
    workers = min(job.options.processes, len(groups))
    pids = context.Array("l", workers)
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker,
                               initargs=(done, pids, os.getpid()))
    memory.watch(pids)
    handover = Handover()
    try:
        dr_motions = dead_reckoning_motions(job.traverse)
        futures: dict[int, Future] = {}

        def submit(g: int, motions: Motions, vo_s: float) -> None:
            nonlocal dr_motions
            state = resume[g] if resume and g < len(resume) else None
            part = save.part(g) if save is not None else None
            # a group whose configurations all take the VO's motions reads no dead reckoning
            reads_dr = not all(uses_vo(kinds) for kinds in groups[g].values())
            fields = stop_records([kind for kinds in groups[g].values() for kind in kinds])
            records = handover.records(f"group-{g}", job.traverse, fields) if fields else None
            inputs = GroupInputs(_job_of(job, groups[g]), state, motions,
                                 dr_motions if reads_dr else Motions([None]), vo_s, records)
            futures[g] = pool.submit(_localize_group_in_worker, handover.write(f"group-{g}", inputs), g, part, start)
            if len(futures) == len(groups) and any(_uses_vo(configs) for configs in groups):
                dr_motions = None  # the groups have them; the run's are the VO's
            release_memory()  # what the inputs' pickling left, and read of the source's mapped arrays
            if len(futures) == len(groups):  # this process only waits for its groups now
                release_library_pages()

        for g, configs in enumerate(groups):
            if not _uses_vo(configs):
                submit(g, dr_motions, 0.0)
        waiting = [g for g, configs in enumerate(groups) if _uses_vo(configs)]
        motions, vo_s = _vo_motions(job, resume, known, pool, progress) if waiting else (Motions(), 0.0)

        def submit_with_motions(g: int) -> None:
            submit(g, motions, vo_s)

        _wait(futures, waiting, submit_with_motions, workers, done, n, progress)
        for f in futures.values():  # the first group that failed, before any that never started
            if f.done() and f.exception() is not None:
                f.result()
        outcomes = [read_once(futures[g].result()) for g in range(len(groups))]
        for configs, outcome in zip(groups, outcomes, strict=True):  # the motions each group was fed
            outcome.motions = motions if _uses_vo(configs) else dr_motions if dr_motions is not None else Motions()
        return outcomes
    except BrokenProcessPool as exc:
        raise GraphError(f"a process running configurations stopped unexpectedly (killed, or out of memory?): "
                         f"{exc}") from None
    finally:
        done[-1] = 1  # when one group failed or the run was interrupted, the others stop at their next stop
        pool.shutdown(wait=True, cancel_futures=True)
        memory.stop()
        handover.cleanup()


@dataclass
class GroupInputs:
    """What a worker needs to run a group: its job, its saved state (when resumed) and the
    motions."""

    job: GroupJob
    state: RunState | None
    motions: Motions
    dr_motions: Motions
    vo_s: float
    records: StopRecords | None = None  # the image records its configurations read, a stop at a time


MAPPED_BYTES = 1 << 20  # an input array this large is mapped from one file by every worker


class Handover:
    """Groups' inputs handed to their workers in files: not through the pool's queue, whose
    feeder thread keeps the last message it pickled (tens of MB) until the next one, for the rest
    of the run. Each large array (the truth's landmarks) is written once and mapped read-only by
    every worker that reads it, one copy in the page cache instead of one in each process."""

    def __init__(self):
        self._folder = temporary_folder("groups")
        self.folder = Path(self._folder.name)
        # by id; the array is held too, so that no other object takes its id meanwhile
        self._arrays: dict[int, tuple[np.ndarray, Path]] = {}

    WHAT = "a group's inputs for its worker (in the system's temporary folder; TMPDIR chooses another)"

    def write(self, name: str, inputs: GroupInputs) -> Path:
        path = self.folder / f"{name}.pickle"
        with writing(path, self.WHAT), open(path, "wb") as f:  # pickled in frames straight to the file
            _HandoverPickler(f, self).dump(inputs)
        return path

    def records(self, name: str, traverse: Traverse, fields: set[str]) -> StopRecords:
        path = self.folder / f"{name}-records.pickle"
        with writing(path, self.WHAT):
            return StopRecords.write(path, traverse, fields)

    def array_file(self, array: np.ndarray) -> Path:
        if id(array) not in self._arrays:
            path = self.folder / f"array-{len(self._arrays)}.npy"
            np.save(path, array, allow_pickle=False)
            self._arrays[id(array)] = (array, path)
        return self._arrays[id(array)][1]

    def cleanup(self) -> None:
        self._arrays.clear()
        self._folder.cleanup()  # a worker's mapping outlives the file's name


class _HandoverPickler(pickle.Pickler):
    def __init__(self, file, handover: Handover):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.handover = handover

    def reducer_override(self, obj):
        if type(obj) is np.ndarray and obj.nbytes >= MAPPED_BYTES and not obj.dtype.hasobject:
            return _mapped_array, (str(self.handover.array_file(obj)),)
        return NotImplemented


def _mapped_array(path: str) -> np.ndarray:
    return map_npy(Path(path))  # read-only: a write into an input raises


def read_once(path: Path) -> GroupInputs | GroupOutcome:
    """A group's inputs (in its worker) or outcome (in the run's process), read from the file
    the other side wrote; the file goes (a mapped input array stays until the run ends)."""
    with open(path, "rb") as f:
        handed = pickle.load(f)
    path.unlink()
    return handed


def _job_of(job: GroupJob, configs: dict[str, list[str]]) -> GroupJob:
    """A group's job, its traverse without image records: the motions are given, so no stereo,
    and the panoramas, HRC frames and ground patches its configurations read come a stop at a
    time (StopRecords): most of a traverse's pickle is its stereo and panoramas."""
    return replace(job, configs=configs, traverse=job.traverse.keeping(set()))


def _uses_vo(configs: dict[str, list[str]]) -> bool:
    return any(uses_vo(kinds) for kinds in configs.values())


def dead_reckoning_motions(traverse: Traverse) -> Motions:
    slip = traverse.wheel_slip
    motions = Motions([None])
    for k in range(1, len(traverse.stops)):
        motions.append(dead_reckoning_motion(traverse.stops[k], motions[-1], slip))
    return motions


def _vo_motions(job: GroupJob, resume: list[RunState] | None, known: VoMotions | None, pool: ProcessPoolExecutor,
                progress: ProgressCallback | None) -> tuple[Motions, float]:
    """Every stop's VO motion (bridged where VO fails) and the seconds it took: from a saved
    group with VO that has them all, from the source, or estimated in blocks over the pool."""
    traverse = job.traverse
    n, slip = len(traverse.stops), traverse.wheel_slip
    for state in resume or ():
        if len(state.motions) == n and any(loc.uses_vo for loc in state.localizers.values()):
            return state.motions, state.vo_s
    if known is not None:
        return Motions(known.motions), known.seconds
    t0 = time.perf_counter()
    ahead = VoAhead(traverse, job.estimator, 1, pool)
    motions = Motions([None])
    for k in range(1, n):
        motions.append(motion_from(ahead.result(k), traverse.stops[k], motions[-1], slip))
        if progress is not None and (k % BLOCK_STOPS == 0 or k == n - 1):
            progress("stereo VO", k, n - 1)
        if k % RELEASE_EVERY_STOPS == 0:  # the stereo observations sent to the VO so far
            release_mapped_pages()
    return motions, time.perf_counter() - t0


def _wait(futures: dict[int, Future], waiting: list[int], submit: Callable[[int], None], workers: int, done,
          n: int, progress: ProgressCallback | None) -> None:
    """Until every group has run: the `waiting` ones submitted one at a time as a worker comes
    free (a job queued in the pool is held pickled, its traverse, in this process); the first
    to fail stops the wait before another is submitted (its error is raised by its result)."""
    while True:
        if any(f.done() and f.exception() is not None for f in futures.values()):
            return
        running = [f for f in futures.values() if not f.done()]
        if waiting and len(running) < workers:
            submit(waiting.pop(0))
            continue  # look for a failure again before the next
        if not running:
            return
        wait(running, timeout=0.5, return_when=FIRST_COMPLETED)
        if progress is not None:
            progress(f"stops ({len(futures) + len(waiting)} groups side by side)", min(done[:-1]), n)


class MemoryWatch:
    """The largest sum of the resident memory of this process and its workers, sampled four
    times a second (Linux; None elsewhere): what the run asked of the machine at once. The
    sum of each process's own peak would add peaks that came at different times."""

    def __init__(self):
        self.peak_mb: float | None = None
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None

    def watch(self, pids) -> None:
        self._thread = threading.Thread(target=self._sample, args=(pids,), daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        if self._thread is not None:
            self._thread.join()

    def _sample(self, pids) -> None:
        while not self._stopped.wait(0.25):
            # None: not Linux, or the worker has gone
            total = sum(rss_mb(pid) or 0.0 for pid in [os.getpid(), *(p for p in pids[:] if p)])
            if total:
                self.peak_mb = max(self.peak_mb or 0.0, total)


def _start_worker(done, pids, run_pid: int) -> None:
    global _stops_done, _run_pid
    _stops_done, _run_pid = done, run_pid
    hold_malloc_thresholds()
    with pids.get_lock():
        free = list(pids[:]).index(0)
        pids[free] = os.getpid()
    # gone with the run (killed: stop before its resumption starts saving too), and when the run
    # was interrupted or another group failed
    watch_the_run(run_pid, also=lambda: bool(_stops_done[-1]))


def _stop_if_the_run_stopped() -> None:
    """At a stop: exit when the run's process is gone, was interrupted, or another group failed
    (the watch does the same between stops)."""
    if _stops_done is not None and _stops_done[-1]:
        os._exit(1)
    try:
        os.kill(_run_pid, 0)
    except ProcessLookupError:
        os._exit(1)


def _localize_group_in_worker(inputs_path: Path, index: int, save: Checkpoints | None, start: float) -> Path:
    inputs = read_once(inputs_path)
    job, state, motions, records = inputs.job, inputs.state, inputs.motions, inputs.records
    if save is not None:
        save.refer_to(job.traverse, job.truth)
    if state is None:
        state = new_state(job)
        state.dr_motions, state.vo_s = inputs.dr_motions, inputs.vo_s
        if len(motions) > len(state.motions):
            state.motions = motions  # as read: their columns mapped, not copied
    elif len(state.motions) < len(motions):  # a saved group has the motions up to its stop
        state.motions.extend(motions[k] for k in range(len(state.motions), len(motions)))

    def progress(stage: str, k: int, total: int) -> None:
        _stop_if_the_run_stopped()
        if stage == "stops" and _stops_done is not None:
            _stops_done[index] = k

    outcome = localize_group(job, state, None, save, progress, None, start, f"group {index + 1}", records)
    outcome.motions = Motions()  # the run's process has them: a traverse's worth of motions not sent back
    # Into a file, in frames, not back through the pool's pipe, which pickles it whole into
    # memory first: a group's results on the mission, in the worker at its end and in the run's
    # process as it reads them.
    path = inputs_path.with_name(f"outcome-{index}.pickle")
    with writing(path, "a group's results for the run's process"), open(path, "wb") as f:
        pickle.dump(outcome, f, protocol=pickle.HIGHEST_PROTOCOL)
    return path
