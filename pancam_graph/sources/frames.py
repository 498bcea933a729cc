"""The image front-end over a sequence of stereo frames: every stop's pair read, rectified and
tracked in order; a bad frame either leaves its stop to the VO bridge or stops the sequence
with what was tracked before it kept."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import Generic, TypeVar

import numpy as np

from ..errors import FrameError, InputError
from ..frontend.tracker import CameraMotion, StereoTracker
from ..records import Stop, Traverse
from ..runtime.processes import heap_for_image_work
from .registry import SourceData

# Reads stop k's (left, right) grayscale pair, rectified; raises InputError naming the file.
ReadPair = Callable[[int], tuple[np.ndarray, np.ndarray]]
Item, Read = TypeVar("Item"), TypeVar("Read")


@heap_for_image_work()  # images and their buffers from the heap (runtime/processes.py)
def track_frames(stops: Sequence[Stop], read_pair: ReadPair, tracker: StereoTracker,
                 finish: Callable[[list[Stop], list[str]], SourceData], skip_bad_frames: bool = False,
                 progress: Callable[[str, int, int], None] | None = None,
                 camera_motion: Callable[[np.ndarray], CameraMotion] | None = None) -> SourceData:
    """`finish(tracked stops, notes)` builds the source's data from the stops tracked so far.
    `camera_motion(body previous_T_current)`: with the stops' dead reckoning, the tracker looks
    for each track where the rover's own motion estimate puts it.

    A frame that cannot be read: with `skip_bad_frames` its stop gets no observations (the VO
    bridges it) and a note; otherwise FrameError, whose `partial` is `finish` of the stops before."""
    tracked: list[Stop] = []
    notes: list[str] = []
    moved: np.ndarray | None = None  # the body's dead-reckoned motion since the last tracked frame
    for stop, reading in read_ahead(stops, lambda stop: read_pair(stop.index)):
        step = stop.dead_reckoning
        moved = None if moved is None or step is None else moved @ step.prev_T_curr
        try:
            pair = reading.result()
        except InputError as exc:
            if not skip_bad_frames:
                partial = finish(tracked, notes) if tracked else None
                raise FrameError(f"stop {stop.index}: {exc}", stop.index, partial) from None
            notes.append(f"stop {stop.index} skipped: {exc}")
            tracked.append(stop)  # no observations: the VO bridges the stop
        else:
            motion = None if camera_motion is None or moved is None else camera_motion(moved)
            tracked.append(replace(stop, stereo=tracker(*pair, motion)))
            moved = np.eye(4)
        if progress is not None:
            progress("front-end", stop.index + 1, len(stops))
    return finish(tracked, notes)


def read_ahead(items: Sequence[Item], read: Callable[[Item], Read]) -> Iterator[tuple[Item, Future[Read]]]:
    """Each item with the reading of it (`read(item)`, its exception included), read on a
    thread of its own one item ahead: the next images are decoded and rectified while these are
    worked on (OpenCV leaves Python's lock while it works). One reader, in order, so a source
    reads as it would alone."""
    with ThreadPoolExecutor(max_workers=1) as reader:
        readings = [reader.submit(read, item) for item in items[:1]]
        for k, item in enumerate(items):
            if k + 1 < len(items):
                readings.append(reader.submit(read, items[k + 1]))
            yield item, readings.pop(0)


class Ahead(Generic[Item]):
    """An iterator's items made on a thread of its own, at most `depth` ahead of their use:
    work that needs nothing of what the caller does meanwhile (a site's panorama matching while
    the navigation frames are tracked; OpenCV leaves Python's lock while it works). Iterate it
    once, in a `with` block: leaving the block stops the thread after the item it is making."""

    _DONE = object()

    def __init__(self, items: Iterator[Item], depth: int = 1):
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._fill, args=(items,), name="ahead", daemon=True)
        self._thread.start()

    def _fill(self, items: Iterator[Item]) -> None:
        try:
            for item in items:
                if not self._put((item, None)):
                    return
            self._put((self._DONE, None))
        except BaseException as exc:  # handed to the caller, raised where it iterates
            self._put((None, exc))
        finally:
            close = getattr(items, "close", None)
            if close is not None:
                close()

    def _put(self, entry: tuple) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator[Item]:
        while True:
            item, exc = self._queue.get()
            if exc is not None:
                raise exc
            if item is self._DONE:
                return
            yield item

    def __enter__(self) -> Ahead[Item]:
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join()


def frame_ms(tracker: StereoTracker) -> np.ndarray:
    """Time per frame tracked, rectification (when the source rectifies) included."""
    frame = np.asarray(tracker.times.ms.get("frame", [np.nan]))
    rectify = tracker.times.ms.get("rectify")
    if rectify is not None and len(rectify) == len(frame):
        frame = frame + np.asarray(rectify)
    return frame


def median_frame_ms(tracker: StereoTracker) -> float:
    return float(np.median(frame_ms(tracker)))


def odometry_camera_motion(traverse: Traverse) -> Callable[[np.ndarray], CameraMotion]:
    """The navigation camera's motion from the body's (dead reckoning), for the tracker."""
    rig, body_T_camera = traverse.rig, traverse.body_T_nav().matrix()

    def camera_motion(previous_T_current: np.ndarray) -> CameraMotion:
        return CameraMotion.from_body_motion(previous_T_current, body_T_camera, rig.wac, rig.baseline_m)

    return camera_motion
