"""An image folder (docs/observation_format.md, `frames.csv`): a traverse whose navigation
stereo pairs are images. The front-end runs over every frame; GPS, odometry, truth and the
rig come from the folder as in an observation folder. `pancam-graph render` writes one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config import FrontendConfig
from ..errors import InputError
from ..frontend.tracker import StereoTracker
from ..results import SourceInfo
from .base import SourceData


def matches(path: Path) -> bool:
    from ..io.observations import is_image_folder

    return is_image_folder(path)


def read_gray(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A grayscale image of the expected (height, width), or a message naming the file."""
    import cv2

    if not path.is_file():
        raise InputError(f"{path}: missing")
    data = path.read_bytes()
    if path.suffix.lower() == ".png" and not data.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82"):
        raise InputError(f"{path}: truncated PNG (no IEND chunk)")
    if path.suffix.lower() in (".jpg", ".jpeg") and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise InputError(f"{path}: truncated JPEG (no end marker)")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: not a readable image")
    if image.shape != size:
        raise InputError(f"{path}: {image.shape[1]} x {image.shape[0]} px, but the calibration is "
                         f"{size[1]} x {size[0]}")
    return image


def load(folder: Path, frontend: FrontendConfig | None = None,
         progress: Callable[[str, int, int], None] | None = None, skip_bad_frames: bool = False) -> SourceData:
    """`skip_bad_frames`: a missing, truncated or wrong-sized image leaves its stop without
    observations (the VO bridges it) instead of stopping with the message naming the file."""
    from ..io.observations import read_observations

    obs = read_observations(folder)
    traverse = obs.traverse
    cam = traverse.rig.wac
    tracker = StereoTracker(frontend)
    stops, skipped = [], []
    for stop, (left, right) in zip(traverse.stops, obs.frames, strict=True):
        size = (cam.height, cam.width)
        try:
            pair = read_gray(left, size), read_gray(right, size)
        except InputError as exc:
            if not skip_bad_frames:
                raise
            skipped.append(f"stop {stop.index} skipped: {exc}")
            stops.append(stop)  # no observations: the VO bridges the stop
        else:
            stops.append(replace(stop, stereo=tracker(*pair)))
        if progress is not None:
            progress("front-end", stop.index + 1, len(traverse.stops))
    frontend = frontend or FrontendConfig()
    frame_ms = tracker.times.ms.get("frame", [np.nan])
    info = SourceInfo("image_folder", str(folder), "truth.kitti of the image folder" if obs.truth else "none",
                      notes=(f"front-end {frontend.detector}: median {np.median(frame_ms):.1f} ms per frame",
                             *skipped), options={"detector": frontend.detector, "skip_bad_frames": skip_bad_frames})
    return SourceData(replace(traverse, stops=tuple(stops)), obs.truth, obs.estimator, obs.seed, info)
