"""An image folder (docs/observation_format.md, `frames.csv`): a traverse whose navigation
stereo pairs are images. The front-end runs over every frame (rectifying raw images with the
folder's calibration first); GPS, odometry, truth and the rig come from the folder as in an
observation folder. `pancam-graph render` writes one."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import EstimatorConfig, FrontendConfig, SourceOptions
from ..errors import FrameError, InputError
from ..formats.images import read_gray
from ..frontend.motion import VoMotions
from ..frontend.tracker import StageTimes, StereoTracker
from ..records import Stop
from ..runtime.processes import heap_for_image_work
from ..solve.results import SourceInfo
from .frames import Ahead, median_frame_ms, odometry_camera_motion, track_frames
from .registry import Source, SourceData, StereoFrames, frontend_for
from .site_images import MatchedSite, matched_sites, uses_orthoimage, with_site_panoramas

# Pixel sigma of a landmark's views when its tie points were matched across sites from images:
# the matches' error against the renderer's truth has a median of 0.50 px and 96 % below 3 px.
TIE_SIGMA_PX = 1.0
# Pixel sigma of an HRC view of a WAC feature found in the HRC image. The match itself is good to
# 2.3 HRC px RMS along the rows and 0.55 px across them (98 % within 7 px), but it finds where the
# WAC's pixel is, so it carries that pixel's error: one WAC pixel (7 HRC px) is what it is worth.
# At 2 px the copied tie-point errors made vo_sites_hrc worse on denver_trail (docs/frontend.md).
HRC_SIGMA_PX = 7.0

if TYPE_CHECKING:
    from ..store.observation_folder import ObservationSet


def matches(path: Path) -> bool:
    from ..store.observation_folder import is_image_folder

    return is_image_folder(path)


class FramePairs:
    """The stereo pairs of an image folder, read (raw) and rectified."""

    def __init__(self, obs: ObservationSet):
        cam, hrc = obs.traverse.rig.wac, obs.traverse.rig.hrc
        self.size = (cam.height, cam.width)
        self.hrc_size = None if hrc is None else (hrc.height, hrc.width)
        self.frames = obs.frames
        # raw images (lens distortion, a misaligned right camera) are rectified before tracking
        self.rectify = None if obs.calibration is None else obs.calibration.rectification_maps()

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        left, right = self.frames[k]
        return read_gray(left, self.size), read_gray(right, self.size)

    def read_view(self, image) -> tuple[np.ndarray, np.ndarray]:
        """A panorama frame's WAC pair (store.observation_folder.PanoramaImage), rectified."""
        pair = (read_gray(image.left, self.size), read_gray(image.right, self.size))
        return pair if self.rectify is None else self.rectify(*pair)

    def read_hrc(self, image) -> np.ndarray:
        """An HRC frame (store.observation_folder.PanoramaImage of camera "hrc"), as taken: the rig's HRC
        is a pinhole camera."""
        return read_gray(image.left, self.hrc_size)

    def rectified(self, pair: tuple[np.ndarray, np.ndarray], times: StageTimes) -> tuple[np.ndarray, np.ndarray]:
        """A raw pair rectified, the time it took added to `times` (stage "rectify")."""
        start = time.perf_counter()
        rectified = self.rectify(*pair)
        times.add("rectify", start)
        return rectified


def load(folder: Path, frontend: FrontendConfig | None = None,
         progress: Callable[[str, int, int], None] | None = None, skip_bad_frames: bool = False,
         sites: bool = True) -> SourceData:
    """`skip_bad_frames`: a missing, truncated or wrong-sized image leaves its stop without
    observations (the VO bridges it) instead of stopping with the message naming the file.
    `sites`: match the site panoramas into tie points (when the folder has them)."""
    from ..store.observation_folder import read_observations

    obs = read_observations(folder)
    frontend = frontend or FrontendConfig()
    tracker = StereoTracker(frontend)
    pairs = FramePairs(obs)

    def read_pair(k: int) -> tuple[np.ndarray, np.ndarray]:
        pair = pairs.read(k)
        return pair if pairs.rectify is None else pairs.rectified(pair, tracker.times)

    def finish(stops: list[Stop], notes: list[str]) -> SourceData:
        n = len(stops)
        truth = None if obs.truth is None else replace(obs.truth, world_T_body=obs.truth.world_T_body[:n])
        rectified = "rectified with the folder's calibration, " if pairs.rectify is not None else ""
        info = SourceInfo("image_folder", str(folder), "truth.kitti of the image folder" if truth else "none",
                          notes=(*obs.notes, f"front-end {frontend.detector}: {rectified}median "
                                 f"{median_frame_ms(tracker):.1f} ms per frame", *notes),
                          options={"detector": frontend.detector, "skip_bad_frames": skip_bad_frames})
        return SourceData(replace(obs.traverse, stops=tuple(stops)), truth, obs.estimator, obs.seed, info)

    camera_motion = odometry_camera_motion(obs.traverse) if frontend.odometry_aided else None
    if not sites or not any(p.camera == "wac" for p in obs.panorama_frames):
        return track_frames(obs.traverse.stops, read_pair, tracker, finish, skip_bad_frames, progress, camera_motion)
    has_hrc = obs.traverse.rig.hrc is not None and any(p.camera == "hrc" for p in obs.panorama_frames)
    # each site's panorama is matched on a thread of its own while the navigation frames are
    # tracked and the VO estimated: only its ties need the VO. Three sites ahead: one left that
    # thread waiting and the VO's core idle (docs/performance.md)
    matching = matched_sites(obs, len(obs.traverse.stops), pairs.read_view, frontend, skip_bad_frames,
                             pairs.read_hrc if has_hrc else None, uses_orthoimage(obs, obs.estimator))
    with heap_for_image_work(), Ahead(matching, depth=3) as matched:
        data = track_frames(obs.traverse.stops, read_pair, tracker, finish, skip_bad_frames, progress,
                            camera_motion)
        return with_sites(data, obs, pairs, frontend, skip_bad_frames, progress, matched)


def with_sites(data: SourceData, obs: ObservationSet, pairs: FramePairs, frontend: FrontendConfig,
               skip_bad_frames: bool, progress: Callable[[str, int, int], None] | None,
               matched: Iterable[MatchedSite] | None = None) -> SourceData:
    """The site panoramas' features and tie points (sources/site_images.py) added to the tracked
    stops. The ties are found to about 1 px (docs/frontend.md): unless the folder says otherwise,
    the estimator's landmark views get that sigma."""
    estimator = data.estimator
    notes = []
    if estimator.sites.sigma_px is None:
        sites = estimator.sites.model_copy(update={"sigma_px": TIE_SIGMA_PX})
        estimator = estimator.model_copy(update={"sites": sites})
        notes.append(f"tie points matched across sites from images: landmark views at {TIE_SIGMA_PX} px")
    has_hrc = obs.traverse.rig.hrc is not None and any(p.camera == "hrc" for p in obs.panorama_frames)
    if has_hrc and estimator.hrc.sigma_px is None:
        estimator = estimator.model_copy(update={"hrc": estimator.hrc.model_copy(update={"sigma_px": HRC_SIGMA_PX})})
        notes.append(f"WAC features found in the HRC frames: HRC views at {HRC_SIGMA_PX} px")
    if progress is not None:
        progress("stereo VO (tie point predictions)", 0, 1)
    vo = VoMotions.estimate(data.traverse, estimator)
    try:
        stops, report = with_site_panoramas(obs, list(data.traverse.stops), pairs.read_view, vo, frontend,
                                            skip_bad_frames, progress, pairs.read_hrc if has_hrc else None, matched)
    except InputError as exc:  # a panorama frame: every navigation frame's tracking is kept
        raise FrameError(f"site panorama: {exc} (--skip-bad-frames leaves the frame out)", len(data.traverse.stops),
                         data) from None
    info = replace(data.info, notes=(*data.info.notes, report.summary(), *notes, *report.skipped))
    return replace(data, traverse=replace(data.traverse, stops=tuple(stops)), estimator=estimator, info=info,
                   vo_motions=vo)


def _load(text: str, options: SourceOptions, progress) -> SourceData:
    frontend = frontend_for(options)
    return load(Path(text), frontend, progress, bool(options.skip_bad_frames))


# Before observation folders: an image folder is one, with frames.csv for its stereo pairs.
def stereo_frames(folder: Path) -> StereoFrames:
    from ..store.observation_folder import read_observations

    obs = read_observations(folder)
    pairs = FramePairs(obs)
    return StereoFrames(list(obs.traverse.stops), pairs.read, pairs.size,
                        None if pairs.rectify is None else pairs.rectified, odometry_camera_motion(obs.traverse))


def _estimator(text: str) -> EstimatorConfig:
    from ..store.observation_folder import read_estimator

    return read_estimator(Path(text))


SOURCES = (Source("image_folder", 30, frozenset({"detector", "skip_bad_frames"}), matches, _load,
                  "an image folder (traverse.toml with frames.csv)", frames=stereo_frames, estimator=_estimator),)
