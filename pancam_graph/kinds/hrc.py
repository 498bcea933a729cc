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
    pointing_sigma_deg: float | None = Field(
        None, ge=0.0, le=1.0, description="the mast's pointing error of an HRC frame (1 sigma, pan and tilt each), "
        "in every view's weight: 0.0037 deg is 0.8 HRC px; None: as the scenario's [errors] "
        "pan_tilt_resolution_deg says (a uniform error within half of it), 0 without one")


def view_sigma_px(image_sigma_px: float, pointing_sigma_deg: float, hrc_fx_px: float) -> float:
    """An HRC view's pixel sigma: the image's noise and the mast's pointing error in HRC pixels.
    The pointing error moves an HRC frame's views 7 times as many pixels as a WAC frame's: at
    the realistic 0.013 deg resolution 0.8 HRC px against 0.3 of image noise. It is shared by a
    frame's views, but a frame holds few landmark views (mars_traverse seed 20000: about 1,400
    in the graph over 2,700 frames), so it is weighted as each view's own."""
    return float(np.hypot(image_sigma_px, hrc_fx_px * np.deg2rad(pointing_sigma_deg)))


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
        settings: HrcSettings = localizer.estimator.hrc
        self.sigma_px = view_sigma_px(settings.sigma_px or localizer.traverse.image_noise_px,
                                      settings.pointing_sigma_deg or 0.0, self.rig.hrc.fx)
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
