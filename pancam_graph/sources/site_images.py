"""An image folder's site panoramas into the back-end's panorama and HRC observations: every
site's features (frontend/panorama.py), its tie points to the last few sites (frontend/ties.py)
predicted by the stereo VO between the two sites and its covariance (what the `vo`
configuration knows there), its features found in its HRC frames (frontend/hrc.py) and, when
the traverse has an orbital orthoimage, its ground seen from above (frontend/dense_stereo.py)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..config import EstimatorConfig, FrontendConfig
from ..errors import InputError
from ..frontend.dense_stereo import ground_patch
from ..frontend.hrc_matching import HrcMatcher, HrcMatches, hrc_footprints
from ..frontend.motion import VoMotions
from ..frontend.panorama import PanoramaMatcher, PanoramaView, SitePanorama
from ..frontend.ties import TieMatcher, TieResult
from ..graph.tie_gate import RelativePose
from ..kinds.stereo_calibration import StereoCalibration
from ..records import GroundPatch, HrcFrame, PanoramaFrame, StereoObservations, Stop
from ..runtime.processes import heap_for_image_work
from .frames import read_ahead

if TYPE_CHECKING:
    from ..store.observation_folder import ObservationSet

MAX_TIE_DISTANCE_M = 80.0  # sites further apart see no common ground at a usable range
TRACK_OFFSET = 1_000_000_000  # site track ids start here, apart from the navigation tracks'
# The image VO's error between two sites against its covariance (pixel noise alone), the drawn
# calibration's share taken out: normalized RMS 2.5 in yaw and 2.3-2.5 in the horizontal
# translation over 30-step chains (40 m) of rendered realistic short_trail seeds 0-9, 1.3 in roll
# and pitch (docs/frontend.md). The tie prediction's standard deviations are scaled by it.
# Measured against steps that claimed their pixel noise alone: a folder whose estimator widens
# the steps too (vo_sigma_scale, realistic renders since 2026-11-29) has its prediction widened
# by both, about 4.5 times in heading where 2.5 would do. Scaling by what vo_sigma_scale leaves
# (2.5 / 1.8 there) was tried and not kept: on rendered realistic short_trail 0-9 `vo_sites` closed
# at 0.167 % RMS against 0.159 % (seed 1 0.121 -> 0.210, seed 3 0.091 -> 0.068; denver_trail 0 and
# 1 0.142 -> 0.146, 0.118 -> 0.103), the wider gate losing nothing measurable.
PREDICTION_SIGMA_SCALE = 2.5

ReadViewPair = Callable[[object], tuple[np.ndarray, np.ndarray]]  # PanoramaImage -> rectified pair
ReadHrc = Callable[[object], np.ndarray]  # PanoramaImage of an HRC frame -> grey image


@dataclass(frozen=True)
class SitePairTies:
    """The tie points found between an earlier site (a) and a later one (b)."""

    a_stop: int
    b_stop: int
    distance_m: float  # predicted
    prediction: RelativePose
    result: TieResult


@dataclass
class SiteReport:
    """What the site front-end did, for the run's notes and for evaluation."""

    sites: list[SitePanorama] = field(default_factory=list)  # without their images
    pairs: list[SitePairTies] = field(default_factory=list)
    hrc: dict[int, list[HrcMatches]] = field(default_factory=dict)  # per site stop
    skipped: list[str] = field(default_factory=list)  # frames that could not be read

    def summary(self) -> str:
        if not self.sites:
            return "no site panoramas"
        adjacent = [p for p in self.pairs if p.b_stop == self.next_site(p.a_stop)]
        counts = [len(p.result.ties) for p in adjacent]
        seconds = sum(s.seconds for s in self.sites) + sum(p.result.seconds for p in self.pairs)
        links = sum(s.links for s in self.sites)
        text = (f"site panoramas: {len(self.sites)} sites, {links} features linked between overlapping frames; "
                f"{sum(len(p.result.ties) for p in self.pairs)} tie points over {len(self.pairs)} site pairs")
        if counts:
            text += f" (adjacent sites: median {int(np.median(counts))}, fewest {min(counts)})"
        frames = [m for matches in self.hrc.values() for m in matches]
        if frames:
            found = [len(m.track_ids) for m in frames]
            text += (f"; {sum(found)} WAC features found in {len(frames)} HRC frames (median {int(np.median(found))}, "
                     f"fewest {min(found)}; {sum(m.disagreeing for m in frames)} dropped for a shift unlike "
                     "their frame's)")
            seconds += sum(m.seconds for m in frames)
        return text + f"; {seconds:.0f} s"

    def next_site(self, stop: int) -> int | None:
        later = [s.stop for s in self.sites if s.stop > stop]
        return min(later) if later else None


def calibration_sigmas(estimator: EstimatorConfig) -> np.ndarray | None:
    """The stereo pair's calibration error's prior sigmas where a configuration estimates it
    (the tie verification allows for them: frontend/ties.py), None where all trust it."""
    if not any(StereoCalibration.name in kinds for kinds in estimator.configurations.values()):
        return None
    return estimator.stereo_calibration.sigmas()


def images_by_stop(obs: ObservationSet, camera: str = "wac") -> dict[int, list]:
    """The folder's panorama frames (PanoramaImage) of one camera ("wac" pairs or "hrc"), per
    site stop in stop order."""
    by_stop: dict[int, list] = {}
    for image in obs.panorama_frames:
        if image.camera == camera:
            by_stop.setdefault(image.stop, []).append(image)
    return dict(sorted(by_stop.items()))


@dataclass(frozen=True)
class MatchedSite:
    """A site's panorama matched on its own (what needs no VO): its features and their links
    across its frames, and its ground from above."""

    stop: int
    site: SitePanorama
    skipped: tuple[str, ...]  # notes of the frames left out
    ground: GroundPatch | None
    hrc_frames: tuple[tuple[object, np.ndarray], ...] = ()  # (PanoramaImage, grey image) of each HRC frame read


def matched_sites(obs: ObservationSet, n_stops: int, read_pair: ReadViewPair, frontend: FrontendConfig,
                  skip_bad_frames: bool = False, read_hrc: ReadHrc | None = None, orthoimage: bool = False
                  ) -> Iterator[MatchedSite]:
    """Each site of the first `n_stops` stops matched in stop order, its track ids numbered on
    from the last site's (one PanoramaMatcher); with `read_hrc`: its HRC frames read and the
    features under their footprints kept; `orthoimage`: with its ground patch (SGBM on every
    pair, seconds a site, so only when it will be used). A frame that cannot be read raises
    InputError here, or with `skip_bad_frames` is noted and left out."""
    rig = obs.traverse.rig
    matcher = PanoramaMatcher(rig.wac, rig.baseline_m, frontend, first_id=TRACK_OFFSET)
    hrc_images = images_by_stop(obs, "hrc") if read_hrc is not None else {}
    by_stop = [(stop, images) for stop, images in images_by_stop(obs).items() if stop < n_stops]

    def read_site(site: tuple[int, list]) -> tuple[list, list, list[str]]:
        """The site's frames with their pairs, its HRC frames with their images, and the notes
        of those skipped."""
        skipped: list[str] = []
        frames = list(_readable(site[1], read_pair, "frame", skip_bad_frames, skipped))
        hrc = list(_readable(hrc_images.get(site[0], ()), read_hrc, "HRC frame", skip_bad_frames, skipped))
        return frames, hrc, skipped

    # the next site's frames are read while this one is matched
    for (stop, images), reading in read_ahead(by_stop, read_site):
        frames, hrc_frames, skipped = reading.result()
        views = [PanoramaView(im.pan_rad, im.tilt_rad, rig.body_T_left(im.pan_rad, im.tilt_rad).matrix(), *pair)
                 for im, pair in frames]
        # every HRC frame's footprint, read or not: the features a site keeps do not depend on
        # which of its HRC frames could be read
        taken = hrc_images.get(stop, ())
        focus = hrc_footprints(rig, views, [(im.pan_rad, im.tilt_rad) for im in taken]) if taken else None
        site = matcher(stop, images[0].site, views, focus)
        ground = ground_patch(views, rig.wac, rig.baseline_m) if orthoimage and views else None
        yield MatchedSite(stop, site, tuple(skipped), ground, tuple(hrc_frames))


def uses_orthoimage(obs: ObservationSet, estimator: EstimatorConfig) -> bool:
    """Whether the run correlates site ground patches with an orbital orthoimage."""
    return estimator.orbital.use_orthoimage and any(
        m.orthoimage is not None for m in obs.traverse.measurements.get("orbital", ()))


@heap_for_image_work()  # images and their buffers from the heap (runtime/processes.py)
def with_site_panoramas(obs: ObservationSet, stops: list[Stop], read_pair: ReadViewPair, vo: VoMotions,
                        frontend: FrontendConfig, skip_bad_frames: bool = False,
                        progress: Callable[[str, int, int], None] | None = None,
                        read_hrc: ReadHrc | None = None, matched: Iterable[MatchedSite] | None = None
                        ) -> tuple[list[Stop], SiteReport]:
    """The stops with their site panoramas' observations (site ids set), and what was done;
    with `read_hrc`, also the HRC frames' views of the site's features (its tie points
    included). A panorama frame that cannot be read stops with the message naming it, or with
    `skip_bad_frames` is left out of its panorama. `matched`: the sites as `matched_sites`
    gives them for these arguments, already under way (image_folder matches them while the
    navigation frames are tracked); by default matched here."""
    report = SiteReport()
    n_sites = sum(1 for stop in images_by_stop(obs) if stop < len(stops))
    if not n_sites:
        return stops, report
    rig = obs.traverse.rig
    motions = vo.motions
    ties = TieMatcher(rig, obs.traverse.image_noise_px, calibration_sigmas=calibration_sigmas(vo.estimator))
    hrc_matcher = HrcMatcher(rig) if read_hrc is not None and rig.hrc is not None else None
    if matched is None:
        matched = matched_sites(obs, len(stops), read_pair, frontend, skip_bad_frames,
                                read_hrc if hrc_matcher is not None else None, uses_orthoimage(obs, vo.estimator))
    recent: list[SitePanorama] = []
    stops = list(stops)
    for done, one in enumerate(matched):
        stop, site = one.stop, one.site
        report.skipped.extend(one.skipped)
        for earlier in reversed(recent):
            between = range(earlier.stop + 1, stop + 1)
            prediction = RelativePose.compose(
                [(motions[k].prev_T_curr, PREDICTION_SIGMA_SCALE**2 * motions[k].covariance) for k in between],
                [motions[k].calibration_sensitivity for k in between])
            distance = float(np.linalg.norm(prediction.a_T_b.translation()))
            if distance > MAX_TIE_DISTANCE_M:
                continue
            result = ties(earlier, site, prediction)
            _add_ties(site, result)
            report.pairs.append(SitePairTies(earlier.stop, stop, distance, prediction, result))
        hrc = []
        if hrc_matcher is not None:
            hrc = [hrc_matcher(site, im.pan_rad, im.tilt_rad, image) for im, image in one.hrc_frames]
            report.hrc[stop] = hrc
        stops[stop] = replace(stops[stop], site_id=site.site, panorama=tuple(
            PanoramaFrame(v.pan_rad, v.tilt_rad, v.observations) for v in site.views),
            hrc=tuple(HrcFrame(m.pan_rad, m.tilt_rad, m.track_ids, m.uv) for m in hrc), ground=one.ground)
        recent = (recent + [site])[-vo.estimator.sites.memory:]
        report.sites.append(_without_images(site))
        if progress is not None:
            progress("site panoramas", done + 1, n_sites)
    return stops, report


def _readable(images: list, read: Callable, what: str, skip_bad_frames: bool, skipped: list[str]):
    """(frame, what `read` made of it) for each frame; one that cannot be read stops with its
    message or, with `skip_bad_frames`, is noted in `skipped` and left out."""
    for im in images:
        try:
            data = read(im)
        except InputError as exc:
            if not skip_bad_frames:
                raise
            skipped.append(f"site {im.site} {what} skipped: {exc}")
            continue
        yield im, data


def _add_ties(site: SitePanorama, result: TieResult) -> None:
    """Each verified tie becomes the later site's observation of the earlier site's track (once
    per frame)."""
    for index, view in enumerate(site.views):
        there = set(view.observations.track_ids.tolist())
        new = [t for t in result.ties if t.b_view == index and t.track not in there]
        if not new:
            continue
        tracks = {t.track: t for t in new}  # one per track
        o = view.observations
        view.observations = StereoObservations(
            np.concatenate([o.track_ids, np.array(list(tracks), dtype=np.int64)]),
            np.vstack([o.uvv, np.array([t.b_uvv for t in tracks.values()])]))


def _without_images(site: SitePanorama) -> SitePanorama:
    views = [replace(v, left=np.zeros((0, 0), np.uint8), right=np.zeros((0, 0), np.uint8)) for v in site.views]
    return replace(site, views=views)
