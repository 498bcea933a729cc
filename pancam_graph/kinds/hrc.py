"""High-resolution camera views of site landmarks: projection factors with the HRC calibration,
each gated against the WAC landmark first (an HRC false match pulls harder than the WAC can
resist: 7x the angular resolution)."""

from __future__ import annotations

import gtsam
import numpy as np
from pydantic import Field

from ..graph import factors, noise
from ..graph.keys import L
from ..records import Stop, Traverse
from .base import Kind, Section
from .sites import SiteObservations


class HrcSettings(Section):
    """[estimator.hrc]"""

    gate_px: float = Field(30.0, gt=0.0, description="HRC measurement vs WAC landmark prediction")
    sigma_px: float | None = Field(None, gt=0.0, le=50.0, description="pixel sigma of an HRC view; None: the "
                                   "traverse's image noise (WAC features found in HRC images carry the WAC pixel's "
                                   "error: image folders use 7 HRC px, docs/frontend.md)")


class Hrc(Kind):
    name = "hrc"
    order = 4
    needs = {"sites": "it adds views of the site landmarks"}
    counter_defaults = {"hrc_measurements": 0, "rejected_hrc_measurements": 0}
    Settings = HrcSettings

    records = "HRC frames"
    stop_records = frozenset({"hrc"})

    @staticmethod
    def has_records(traverse: Traverse) -> bool:
        return any(s.hrc for s in traverse.stops)

    @classmethod
    def unavailable(cls, traverse: Traverse) -> str | None:
        if traverse.rig.hrc is None:
            return f"rig {traverse.rig.name!r} has no HRC"
        return super().unavailable(traverse)

    def __init__(self, localizer):
        super().__init__(localizer)
        self.rig = localizer.traverse.rig
        self.calibration = self.rig.hrc.gtsam_calibration()
        # HRC residuals start large (landmarks come from the WAC), so only a convex kernel keeps
        # them pulling: Huber, whatever the tie-point kernel is.
        self.sigma_px = localizer.estimator.hrc.sigma_px or localizer.traverse.image_noise_px
        self.huber_k = localizer.estimator.huber_k
        # a tie's matching error is the WAC's, found again in the HRC image: as many HRC pixels
        # as the HRC's focal length is the WAC's
        self.wac_to_hrc_px = self.rig.hrc.fx / self.rig.wac.fx
        self.gate_px = localizer.estimator.hrc.gate_px
        self.added = self.rejected = 0
        localizer.kind("sites").hrc = self

    def collect(self, stop: Stop, obs: SiteObservations) -> None:
        for frame in stop.hrc:
            mount = self.rig.body_T_hrc(frame.pan_rad, frame.tilt_rad)
            for track, uv in zip(frame.track_ids, frame.uv, strict=True):
                obs.hrc[int(track)].append((mount, uv))

    def add_views(self, site: SiteObservations, track: int, world_T_body: gtsam.Pose3, tie_sigma_px: float) -> None:
        """The site's HRC views of a landmark, gated; `tie_sigma_px`: the WAC's matching error of
        the site's views of it (Sites._tie_sigma_px)."""
        views = site.hrc.get(track, ())
        if not views:
            return
        sigma_px = float(np.hypot(self.sigma_px, self.wac_to_hrc_px * tie_sigma_px))
        model = noise.robust("huber", noise.image_pixels(sigma_px), self.huber_k)
        # Predict from this site's own WAC triangulation when it has one: the HRC is 0.4 m from
        # the left WAC, so the WAC's range error hardly moves the point in the HRC image. The
        # graph's landmark may still be the earlier site's triangulation, whose range error at
        # 40 m is hundreds of HRC pixels from here, and would gate out the very measurements
        # that tie the two sites.
        seen = site.points.get(track)
        p_world = (world_T_body.transformFrom(seen.p_body) if seen is not None
                   else self.loc.smoother.point(L(track)))
        for mount, uv in views:
            camera = gtsam.PinholeCameraCal3_S2(world_T_body.compose(mount), self.calibration)
            p_cam = camera.pose().transformTo(p_world)
            if p_cam[2] <= 0 or np.linalg.norm(camera.project(p_world) - uv) > self.gate_px:
                self.rejected += 1
                continue
            self.loc.smoother.add(factors.projection(site.stop, track, uv, self.calibration, mount, model))
            self.added += 1

    def counters(self) -> dict:
        return {"hrc_measurements": self.added, "rejected_hrc_measurements": self.rejected}
