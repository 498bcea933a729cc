"""What a group's run does between stops besides solving them: each stop's results into the
state's tables; at every site, every CHECKPOINT_EVERY_STOPS and after CHECKPOINT_EVERY_S of work
a checkpoint (the garbage
collector settled, the process's memory sampled, the state saved, the run's listener told);
the mapped inputs' pages given back every RELEASE_EVERY_STOPS; progress."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from ..frontend.motion import Motion
from ..records import Stop
from ..runtime.memory import peak_rss_mb, pss_mb, rss_mb, settle_garbage_collector
from ..runtime.processes import RELEASE_EVERY_STOPS, release_mapped_pages
from . import state as checkpoint_policy
from .listener import RunListener
from .localizer import StepResult
from .state import Checkpoints, RunState

ProgressCallback = Callable[[str, int, int], None]

# Reading /proc/self/smaps_rollup (the PSS) takes milliseconds at a resident size of a GB: it is
# read at most every PSS_EVERY_S (docs/performance.md).
PSS_EVERY_S = 2.0
_pss_read_at = -math.inf  # this process's last read (time.monotonic)


class Housekeeping:
    """Listens to a group's stops after the run's own listener (solve.listener.RunListener)."""

    def __init__(self, state: RunState, stops: int, save: Checkpoints | None, listener: RunListener,
                 progress: ProgressCallback | None, start: float):
        self.state, self.stops, self.save, self.listener = state, stops, save, listener
        self.progress, self.start = progress, start
        self.last_checkpoint = time.perf_counter()

    def step(self, stop: Stop, motion: Motion | None, now: dict[str, StepResult]) -> None:
        k = stop.index
        for name, step in now.items():
            self.state.steps[name].append(step)
        now_s = time.perf_counter()
        if (stop.is_site or (k + 1) % checkpoint_policy.CHECKPOINT_EVERY_STOPS == 0
                or now_s - self.last_checkpoint >= checkpoint_policy.CHECKPOINT_EVERY_S):
            self.last_checkpoint = now_s
            self.state.next_stop, self.state.elapsed_s = k + 1, now_s - self.start
            settle_garbage_collector()
            sample_memory(self.state, k)
            if self.save is not None and k + 1 < self.stops:
                self.save(self.state)
            self.listener.checkpoint(stop)
        if (k + 1) % RELEASE_EVERY_STOPS == 0:  # the mapped inputs read so far (the motions, the source's)
            release_mapped_pages()
        if self.progress is not None:
            self.progress("stops", k + 1, self.stops)


def sample_memory(state: RunState, stop: int, last: bool = False) -> None:
    """The process's resident memory at this stop, and its PSS every PSS_EVERY_S (and `last`)."""
    global _pss_read_at
    state.memory_mb.append((stop, rss_mb() or peak_rss_mb()))
    now = time.monotonic()
    if last or now - _pss_read_at >= PSS_EVERY_S:
        _pss_read_at = now
        state.peak_pss_mb = max(state.peak_pss_mb, pss_mb() or 0.0)
