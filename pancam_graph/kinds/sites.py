"""Site panoramas: tie points seen from two or more sites become landmarks with stereo factors.

A candidate tie (a track seen by this site and one of the last few) passes the Mahalanobis tie
gate (graph/tie_gate.py) before it becomes a landmark; later sites' views of a landmark pass the
same test against its first triangulation. Each new landmark is anchored by a weak
bearing-range factor from the site that first triangulated it.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict, deque
from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np
from pydantic import Field

from ..geometry.rig import project_rectified
from ..graph import factors, noise, tie_gate, tie_matching
from ..graph.keys import L, X
from ..graph.tie_gate import RelativePose, SitePoint
from ..records import Stop, Traverse
from ..runtime.spill import Column, mapped
from .base import Kind, Section

# The last sites collected, for the other configurations stepping the same stop (Sites._collect)
_RECENT_SITES: deque[tuple[tuple, Stop, SiteObservations]] = deque(maxlen=4)


@dataclass
class SiteObservations:
    """What one site saw: per track, its stereo and HRC measurements with their camera mounts."""

    stop: int
    stereo: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))
    hrc: dict[int, list[tuple[gtsam.Pose3, np.ndarray]]] = field(default_factory=lambda: defaultdict(list))
    points: dict[int, SitePoint | None] = field(default_factory=dict)  # per track, its body frame


@dataclass(frozen=True)
class LandmarkReference:
    """The site that first triangulated a landmark and that triangulation (its body frame): what
    later views of the landmark must agree with."""

    stop: int
    point: SitePoint


class TrackIds:
    """The tracks made landmarks over the whole traverse (one may not be made again): the latest
    in a set, each `MERGE_AT` before them a sorted array in a file (spill.mapped), 8 bytes each.
    As one set of Python ints they held about 1 KB a stop of long_traverse's vo_sites and full
    (tracemalloc)."""

    MERGE_AT = 4096  # tracks in the set before they go to a file

    def __init__(self) -> None:
        self._latest: set[int] = set()
        self._filed: list[np.ndarray] = []  # sorted, each MERGE_AT tracks

    def add(self, track: int) -> None:
        self._latest.add(track)
        if len(self._latest) >= self.MERGE_AT:
            self._filed.append(mapped(np.sort(np.fromiter(self._latest, np.int64, len(self._latest)))))
            self._latest = set()

    def __contains__(self, track: int) -> bool:
        return track in self._latest or bool(self._in_filed(np.array([track], np.int64))[0])

    def not_in(self, tracks: set[int]) -> list[int]:
        """Those of `tracks` that are not landmark tracks."""
        fresh = np.fromiter(tracks - self._latest, np.int64)
        return fresh[~self._in_filed(fresh)].tolist()

    def _in_filed(self, tracks: np.ndarray) -> np.ndarray:
        # a binary search in each sorted array (np.isin would sort it again at every call)
        found = np.zeros(len(tracks), dtype=bool)
        for filed in self._filed:
            at = np.minimum(np.searchsorted(filed, tracks), len(filed) - 1)
            found |= filed[at] == tracks
        return found

    def __len__(self) -> int:
        return len(self._latest) + sum(len(filed) for filed in self._filed)

    def as_set(self) -> set[int]:
        return self._latest.union(*(filed.tolist() for filed in self._filed))

    def __getstate__(self) -> dict:
        return {"latest": self._latest, "filed": [np.asarray(filed) for filed in self._filed]}

    def __setstate__(self, state: dict) -> None:
        self._latest, self._filed = state["latest"], [mapped(filed) for filed in state["filed"]]


MIN_TIE_WEIGHT = 1e-4  # a tie weighed at the estimate keeps at least this (its sigmas 100 times over)


@dataclass(frozen=True)
class _WeighedTie:
    """A site's stereo view of a landmark weighed at the estimate (Sites.weigh_at_estimate)."""

    stop: int
    track: int
    mount: np.ndarray  # body_T_left, 4x4
    uvv: np.ndarray
    tie_sigma_px: float
    weight: float


class SitesSettings(Section):
    """[estimator.sites]"""

    points_per_site: int = Field(150, ge=3, description="tie points kept per site")
    sigma_px: float | None = Field(None, gt=0.0, le=50.0, description="pixel sigma of a landmark's stereo views "
                                   "at sites; None: the traverse's image noise (tie points matched across sites "
                                   "from images are found to about 1 px: docs/frontend.md)")
    memory: int = Field(3, ge=1, description="earlier sites searched for tie points")
    anchor_sigma_m: float = Field(3.0, gt=0.0, description="bearing-range anchor of a new landmark from its first "
                                  "site, along and across the line of sight")
    kernel: Literal["huber", "cauchy", "none"] = "huber"
    weights: Literal["linearization", "estimate"] = Field(
        "linearization", description="where the kernel weighs a tie: where iSAM2 linearized it (GTSAM's Robust "
        "model), or at the estimate, after every site's update (a Gaussian tie replaced when its weight moves by "
        "0.1; consistent where the first is cautious, but it diverged 31 km into a 100 km mission, where the "
        "first did not: docs/performance.md)")
    tie_error: Literal["pixel_noise", "measured"] | None = Field(
        None, description="a landmark's views at a later site: pixel_noise, weighted as sigma_px alone; measured, "
        "with the image matcher's measured error at that distance from the site before, the same in both eyes "
        "(graph/tie_matching.py); None: as the scenario's [errors] tie_matching says (pixel_noise without one)")


class Sites(Kind):
    name = "sites"
    order = 3
    cost = 3.0
    stop_records = frozenset({"panorama"})
    step_counters = {"new_landmarks": 0, "rejected_ties": 0}
    counter_defaults = {"landmarks": 0, "rejected_tie_points": 0, "rejected_tie_views": 0, "reweighed_ties": 0}
    Settings = SitesSettings

    records = "site panoramas"

    @classmethod
    def scenario_unavailable(cls, scenario) -> str | None:
        return None if scenario.sites.enabled else "the scenario has no site panoramas (its [sites] is not enabled)"

    @staticmethod
    def has_records(traverse: Traverse) -> bool:
        return any(s.is_site for s in traverse.stops)

    def __init__(self, localizer):
        super().__init__(localizer)
        est = localizer.estimator
        self.rig = localizer.traverse.rig
        # the pixel sigma of a landmark's views: the tie noise and the tie gate's triangulations
        settings: SitesSettings = est.sites
        self.sigma_px = settings.sigma_px or localizer.traverse.image_noise_px
        self.memory = settings.memory
        self.anchor_sigma_m = settings.anchor_sigma_m
        self.tie_points_per_site = settings.points_per_site
        # the tie noise as plain values too: a kind's Python factor (site_stereo_factor) is made
        # again from them at a checkpoint, and from the camera's numbers
        kernel_k = est.kernel_k(settings.kernel)
        self.kernel = (settings.kernel, kernel_k)
        self.measured_tie_error = settings.tie_error == "measured"
        self.weigh_at_estimate = settings.weights == "estimate" and settings.kernel != "none"
        self._m_estimator = (noise.robust(settings.kernel, noise.stereo_pixels(1.0), kernel_k).robust()
                             if self.weigh_at_estimate else None)
        self._weighed: dict[tuple[int, int], _WeighedTie] = {}  # ticket -> a tie weighed at the estimate
        self.reweighed = 0
        # per landmark in the window, where the last site that viewed it was (its tie error grows
        # with the distance from there)
        self._last_viewed_from: dict[int, np.ndarray] = {}
        self.stereo_calibration = self.rig.stereo_calibration()
        wac = self.rig.wac
        self.camera = (wac.fx, wac.fy, wac.cx, wac.cy, self.rig.baseline_m)
        self.sites: list[SiteObservations] = []
        self.landmark_ids = TrackIds()
        # (track, site stop) of every stereo view of a landmark, as they came: two columns, not a
        # list a landmark (long_traverse's vo_sites: 61,360 views of 30,010 landmarks)
        self._view_tracks, self._view_stops = Column("q"), Column("q")
        self.references: dict[int, LandmarkReference] = {}
        self._relative_cache: dict[tuple[int, int], RelativePose] = {}  # these two: one site's step
        self._site_poses: dict[int, gtsam.Pose3] = {}
        self.rejected_ties = 0  # candidate tie points whose two sites disagree
        self.rejected_tie_views = 0  # later sites' views of a landmark that disagree with it
        self.hrc = None  # the HRC kind, when the configuration has it, adds its views of landmarks

    def __getstate__(self) -> dict:
        # A pickled Cal3_S2Stereo aborts the process when it is loaded (GTSAM 4.3's bindings);
        # the rig makes it again.
        return {k: v for k, v in vars(self).items() if k != "stereo_calibration"}

    def __setstate__(self, state: dict) -> None:
        vars(self).update(state)
        self.stereo_calibration = self.rig.stereo_calibration()

    def update_before(self, stop: Stop) -> str | None:
        # The gate needs this site's pose in the Bayes tree (its relative covariance to the
        # earlier sites); the motion factor alone puts it there. That update may move the
        # smoother's window on: the sites that left it can take no new factor.
        return "before its tie points" if stop.is_site else None

    def add(self, stop: Stop, counts) -> None:
        if stop.is_site:
            counts["new_landmarks"], counts["rejected_ties"] = self._add_site(stop)

    # -- one site ------------------------------------------------------------------------------

    def _collect(self, stop: Stop) -> SiteObservations:
        """The site's views and triangulations. Every configuration with sites steps the same
        stop one after another: the last few are kept for the others (read-only), keyed by the
        stop and what makes them differ (the pixel sigma, HRC views or not)."""
        key = (self.sigma_px, self.hrc is not None)
        for cached_key, cached_stop, obs in _RECENT_SITES:
            if cached_key == key and cached_stop is stop:
                return obs
        obs = self._collect_anew(stop)
        _RECENT_SITES.append((key, stop, obs))
        return obs

    def _collect_anew(self, stop: Stop) -> SiteObservations:
        obs = SiteObservations(stop.index, stereo=tie_gate.panorama_views(stop, self.rig))
        if self.hrc is not None:
            self.hrc.collect(stop, obs)
        obs.points = tie_gate.site_points(obs.stereo, self.rig, self.sigma_px)
        return obs

    def _calibrated_point(self, site: SiteObservations, track: int, point: SitePoint) -> np.ndarray:
        """Where the site puts the track through the pair as estimated now (Host.site_stereo_pixels):
        the anchor's bearing and range. Through the nominal pair, a turn of the right camera by
        0.02 deg moves a point 40 m away about a metre in range, and thousands of anchors at 3 %
        of a view's weight each pulled the estimated calibration back towards the nominal one
        (the baseline's error and the turn about the vertical: docs/simulation_errors.md)."""
        if self.loc.site_stereo_pixels is None:
            return point.p_body
        corrected = tie_gate.site_points(tie_gate.corrected_views({track: site.stereo[track]},
                                                                  self.loc.site_stereo_pixels), self.rig, self.sigma_px)
        return point.p_body if corrected.get(track) is None else corrected[track].p_body

    def site_pose(self, stop: int) -> gtsam.Pose3:
        """A site's current pose estimate (cached for this site's step)."""
        if stop not in self._site_poses:
            self._site_poses[stop] = self.loc.smoother.pose(X(stop))
        return self._site_poses[stop]

    def _relative(self, a: int, b: int) -> RelativePose:
        """Site pose b seen from site pose a, with its covariance (cached for this site's step)."""
        if (a, b) not in self._relative_cache:
            joint = self.loc.smoother.joint_marginal_covariance(X(a), X(b))
            self._relative_cache[(a, b)] = RelativePose.from_joint(self.site_pose(a), self.site_pose(b), joint)
        return self._relative_cache[(a, b)]

    def _agrees(self, reference: LandmarkReference, stop: int, seen: SitePoint) -> bool:
        d2 = tie_gate.disagreement2(reference.point, seen, self._relative(reference.stop, stop))
        return d2 <= tie_gate.AGREEMENT_GATE

    def after_update(self, stop: Stop, counts) -> str | None:
        if stop.is_site and self.weigh_at_estimate and self._reweigh():
            return "its ties weighed at the estimate"
        return None

    def _add_site(self, stop: Stop) -> tuple[int, int]:
        current = self._collect(stop)
        recent = [site for site in self.sites[-self.memory:] if self.loc.smoother.live(X(site.stop))]
        candidates: dict[int, SiteObservations] = {}
        for earlier in recent:
            for track in self.landmark_ids.not_in(earlier.stereo.keys() & current.stereo.keys()):
                candidates.setdefault(track, earlier)
        tracks = sorted(candidates)
        if len(tracks) > self.tie_points_per_site:
            tracks = sorted(self.loc.rng.choice(tracks, self.tie_points_per_site, replace=False).tolist())

        self._relative_cache.clear()
        self._site_poses.clear()
        added = rejected = 0
        for track in tracks:
            earlier = candidates[track]
            then, now = earlier.points[track], current.points[track]
            if then is None or now is None:
                rejected += 1
                continue
            reference = LandmarkReference(earlier.stop, then)
            if not self._agrees(reference, current.stop, now):
                rejected += 1
                continue
            anchor = self._calibrated_point(earlier, track, then)
            self.loc.smoother.insert(L(track), self.site_pose(earlier.stop).transformFrom(anchor),
                                     leaves_with=X(earlier.stop))
            self.loc.smoother.add(factors.landmark_anchor(earlier.stop, track, anchor, self.anchor_sigma_m))
            self.landmark_ids.add(track)
            self.references[track] = reference
            for site in recent:
                self._add_observations(site, track, gated=site is not earlier)
            self._add_observations(current, track, gated=False)
            added += 1
        # Landmarks already in the graph (tied earlier) seen again from here, unless they or the
        # site they are gated against left the window (those in it are those with a reference); a
        # landmark that did is forgotten (no factor will touch it again). A landmark leaves with
        # its first site, except one tied as that site was leaving (Smoother.insert): it can
        # outlive the site.
        live = self.loc.smoother.live
        self.references = {t: r for t, r in self.references.items() if live(L(t)) and live(X(r.stop))}
        tied_now = set(tracks)
        for track in sorted(t for t in current.stereo.keys() if t in self.references and t not in tied_now):
            self._add_observations(current, track, gated=True)
        self._last_viewed_from = {t: p for t, p in self._last_viewed_from.items() if t in self.references}

        self.rejected_ties += rejected
        self.sites.append(current)
        # Only the last `memory` sites are searched for ties again: drop the older ones' views.
        if len(self.sites) > self.memory:
            self.sites = self.sites[-self.memory:]
        return added, rejected

    def _add_observations(self, site: SiteObservations, track: int, gated: bool) -> None:
        """The site's stereo (and, with the HRC kind, HRC) measurements of a landmark. `gated`: the
        stereo ones only if they agree with the landmark's reference triangulation."""
        stereo = site.stereo.get(track, ())
        if stereo and gated:
            seen = site.points[track]
            if seen is None or not self._agrees(self.references[track], site.stop, seen):
                self.rejected_tie_views += 1
                stereo = ()
        hrc_views = len(site.hrc.get(track, ())) if self.hrc is not None else 0
        tie_sigma_px = self._tie_sigma_px(site, track, len(stereo) + hrc_views)
        for mount, uvv in stereo:
            uvv = np.asarray(uvv, dtype=float)
            if self.weigh_at_estimate:  # full weight for the site's update, then weighed (after_update)
                self._add_weighed(_WeighedTie(site.stop, track, mount.matrix(), uvv, tie_sigma_px, 1.0))
            else:
                self.loc.smoother.add(*self._tie_factor(site.stop, track, mount.matrix(), uvv,
                                                        (*self.kernel, self.sigma_px, tie_sigma_px)))
        if stereo:
            self._view_tracks.append(track)
            self._view_stops.append(site.stop)
            self._last_viewed_from[track] = self.site_pose(site.stop).translation()
        if self.hrc is not None:
            self.hrc.add_views(site, track, self.site_pose(site.stop), tie_sigma_px)

    def _tie_factor(self, stop: int, track: int, mount: np.ndarray, uvv: np.ndarray,
                    model: tuple[str, float | None, float, float]):
        """A site's stereo view (u_left, u_right, v) of a landmark through the mount body_T_left
        (4x4) as a factor, with `model` = (kernel, k, sigma_px, tie_sigma_px), and its recipe: the
        kind's that builds the sites' stereo factors with its shared variables (a Python
        CustomFactor, made again from the recipe at a checkpoint), or GTSAM's (no recipe)."""
        build = self.loc.site_stereo_factor
        if build is None:
            kernel, k, sigma_px, tie_sigma_px = model
            noise_model = noise.robust(kernel, noise.stereo_tie(sigma_px, tie_sigma_px), k)
            return factors.stereo(stop, track, uvv, self.stereo_calibration, gtsam.Pose3(mount), noise_model), None
        arguments = (X(stop), L(track), uvv, self.camera, mount, model)
        return build(*arguments), (build, arguments)

    def _add_weighed(self, tie: _WeighedTie, ticket: tuple[int, int] | None = None) -> None:
        """A tie as a Gaussian factor whose sigmas carry its weight; in place of `ticket`'s."""
        scale = 1.0 / np.sqrt(tie.weight)
        factor, rebuild = self._tie_factor(tie.stop, tie.track, tie.mount, tie.uvv,
                                           ("none", None, self.sigma_px * scale, tie.tie_sigma_px * scale))
        smoother = self.loc.smoother
        if ticket is None:
            ticket = smoother.add(factor, rebuild, tracked=True)
        else:
            ticket = smoother.replace(ticket, factor, rebuild)
        self._weighed[ticket] = tie

    def _reweigh(self) -> bool:
        """Each tie in the window weighed by the kernel at the estimate, after its site's update;
        one whose weight moved by more than 0.1 replaced by one with the new weight: iteratively
        reweighted least squares, one step a site, which iSAM2's linearization points do not bend.
        Weighed only at the next site instead, false ties pulled at full weight until then (up to
        383 sigma out on a realistic short_trail). Whether any was replaced (the replacements wait
        for an update)."""
        smoother = self.loc.smoother
        for ticket, tie in list(self._weighed.items()):
            if not (smoother.live(X(tie.stop)) and smoother.live(L(tie.track))):
                del self._weighed[ticket]
                smoother.forget(ticket)
        if not self._weighed:
            return False
        tickets, ties = list(self._weighed), list(self._weighed.values())
        residuals = self._residuals_at_estimate(ties)
        replaced = 0
        for ticket, tie, residual in zip(tickets, ties, residuals, strict=True):
            weight = max(float(self._m_estimator.weight(residual)), MIN_TIE_WEIGHT)
            if abs(weight - tie.weight) > 0.1:
                del self._weighed[ticket]
                self._add_weighed(dataclasses.replace(tie, weight=weight), ticket)
                replaced += 1
        self.reweighed += replaced
        return replaced > 0

    def _residuals_at_estimate(self, ties: list[_WeighedTie]) -> np.ndarray:
        """The ties' whitened residual norms at unit weight, at the current estimate: each landmark
        projected through its view's mount from its site's pose, against the measured pixels as
        the calibrated pair would have seen them (Host.site_stereo_pixels)."""
        smoother = self.loc.smoother
        estimate = smoother.window_estimate()
        # each site's pose and each landmark looked up once (a few sites, thousands of views)
        stops, at_stop = np.unique([t.stop for t in ties], return_inverse=True)
        tracks, of_track = np.unique([t.track for t in ties], return_inverse=True)
        world_T_body = np.tile(np.eye(4), (len(ties), 1, 1))
        world_T_body[:, :3, :] = smoother.stacked(estimate, [X(int(k)) for k in stops], 12).reshape(-1, 3, 4)[at_stop]
        points = smoother.stacked(estimate, [L(int(t)) for t in tracks], 3)[of_track]
        world_T_left = world_T_body @ np.array([t.mount for t in ties])
        rotation, translation = world_T_left[:, :3, :3], world_T_left[:, :3, 3]
        in_left = np.einsum("nji,nj->ni", rotation, points - translation)
        measured = np.array([t.uvv for t in ties])
        if self.loc.site_stereo_pixels is not None:
            measured = self.loc.site_stereo_pixels(measured)
        error = project_rectified(in_left, self.rig.wac, self.rig.baseline_m) - measured
        covariance = noise.stereo_tie_covariance(self.sigma_px, np.array([t.tie_sigma_px for t in ties]))
        squared = np.einsum("ni,ni->n", error, np.linalg.solve(covariance, error[:, :, None])[:, :, 0])
        return np.where(np.isfinite(squared), np.sqrt(np.abs(squared)), np.inf)  # behind the camera: no weight

    def _tie_sigma_px(self, site: SiteObservations, track: int, views: int) -> float:
        """The matching error (px per axis, 1 sigma) of each of the site's `views` of a landmark an
        earlier site viewed: the matcher's at the distance between the two (zero for its first
        site's views, or with the views weighted as pixel noise alone). The site's views of it
        (overlapping frames, its HRC views) share one error: weighted each as its own, n views
        would count it n times, so each takes it n times over (the variance of their mean)."""
        before = self._last_viewed_from.get(track)
        if not self.measured_tie_error or before is None:
            return 0.0
        distance_m = float(np.linalg.norm(self.site_pose(site.stop).translation() - before))
        return tie_matching.sigma_px(distance_m) * np.sqrt(max(views, 1))

    def landmarks(self) -> set[int]:
        return self.landmark_ids.as_set()

    def tie_links(self) -> np.ndarray:
        """(track, site stop) for every landmark and every site whose panorama observed it, by
        track and then as the sites came."""
        tracks = self._view_tracks.to_numpy()
        order = np.argsort(tracks, kind="stable")
        return np.column_stack([tracks[order], self._view_stops.to_numpy()[order]])

    def counters(self) -> dict:
        return {"landmarks": len(self.landmark_ids), "rejected_tie_points": self.rejected_ties,
                "rejected_tie_views": self.rejected_tie_views, "reweighed_ties": self.reweighed}
