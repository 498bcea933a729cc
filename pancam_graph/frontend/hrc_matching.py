"""A site's WAC features found in its HRC frames, across the ~7x scale difference (the dissertation's section
4.3.2), giving HRC projection measurements of the WAC tracks.

Each WAC feature with a stereo triangulation is predicted into the HRC frame through the mast
(the HRC is 0.4 m from the left WAC, so the WAC's range error moves the prediction little).
The HRC image is then brought to the WAC's geometry around the feature: blurred to the WAC's
resolution and resampled through the homography of the local ground (level in the body
frame) through the point. That synthetic WAC patch is correlated (NCC) with the WAC's own patch
within a few WAC pixels of the prediction; the peak, refined to sub-pixel, maps back into the
HRC image. The HRC pixel found is where the WAC's pixel is: it carries that pixel's error
(docs/frontend.md, "What the HRC views are worth from images"). The frame's matches are then
checked against each other: they sit where predicted plus one shift, the mast's pointing error,
give or take the parallax of the WAC's range error, and a match whose offset is unlike the
frame's median shift by more than that is dropped.

Seed 4.3.2 detects scale-space Harris corners in both images (sigma_d 1 for the WAC, about 7 for
the HRC) and searches along the epipolar line. Predicting through the mast and correlating at
the WAC's scale needs no detector in the HRC at all, and so finds every WAC feature the HRC
sees, not only those that are corners at both scales (refining each match as a corner in the
HRC's own pixels at the WAC's scale was measured: fewer matches, no better estimate).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry.rig import Rig, triangulation_covariance
from ..graph import chi2
from ..orbital.ortho_registration import peak_offset
from .panorama import PanoramaView, Region, SitePanorama


@dataclass(frozen=True)
class HrcSettings:
    # WAC pixels either side of the feature in the correlated patch (21 x 21 px at NCC 0.80 with
    # the frame's check below: the comparison is in docs/frontend.md)
    patch_px: int = 10
    search_px: int = 4  # WAC pixels either side of the prediction searched (mast errors of 0.1 deg: 3 px)
    min_ncc: float = 0.80
    # The frame's own check: a frame's matches sit where predicted plus one shift (the mast's
    # pointing error) and the parallax of the WAC's range error (the HRC is 0.4 m from the left
    # WAC). A match whose offset from the frame's median shift is beyond the 99 % ellipse of
    # that range error and `agreement_sigma_px` (WAC px) is dropped (docs/frontend.md).
    agreement_sigma_px: float = 0.5  # WAC px: the feature's and the peak's error, and the stereo disparity's
    agreement_chi2: float = chi2.quantile(0.99, 2)
    min_frame_matches: int = 5  # fewer matches than this: no shift to check them by, none kept
    min_texture_dn: float = 3.0  # the WAC patch's standard deviation: below it, no position to find
    min_range_m: float = 2.0
    blur_per_scale: float = 0.6  # Gaussian sigma (HRC px) per unit of HRC/WAC scale: a WAC pixel and its optics


@dataclass
class HrcMatches:
    """One HRC frame's measurements of the site's WAC tracks, and what matching did."""

    pan_rad: float
    tilt_rad: float
    track_ids: np.ndarray  # (M,)
    uv: np.ndarray  # (M, 2) HRC pixels
    wac_view: np.ndarray  # (M,) index of the site view whose feature was matched
    wac_uv: np.ndarray  # (M, 2) that feature's rectified left pixel
    predicted: int = 0  # WAC features predicted inside the frame
    seconds: float = 0.0
    ncc: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) each match's correlation peak
    texture_dn: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) its WAC patch's standard deviation
    shift_px: np.ndarray = field(default_factory=lambda: np.zeros(2))  # median of found - predicted: the mast's error
    disagreeing: int = 0  # matches dropped for a shift unlike the frame's


class HrcMatcher:
    """WAC features of a site into its HRC frames."""

    def __init__(self, rig: Rig, settings: HrcSettings | None = None):
        self.rig = rig  # with an HRC
        self.settings = settings or HrcSettings()
        self.scale = rig.hrc.fx / rig.wac.fx

    def __call__(self, site: SitePanorama, pan_rad: float, tilt_rad: float, image: np.ndarray) -> HrcMatches:
        start = time.perf_counter()
        s = self.settings
        hrc = self.rig.hrc
        k_h, wac_k_inv = hrc.matrix(), np.linalg.inv(self.rig.wac.matrix())
        blurred = cv2.GaussianBlur(image.astype(np.float32), (0, 0), s.blur_per_scale * self.scale)
        hrc_T_body = np.linalg.inv(self.rig.body_T_hrc(pan_rad, tilt_rad).matrix())
        margin = (s.patch_px + s.search_px + 1) * self.scale
        seen: set[int] = set()
        ids, uvs, views, wac_uvs, nccs, textures, predictions = [], [], [], [], [], [], []
        points_cam, points_hrc, hrc_R_cams = [], [], []  # each match's WAC triangulation, in both cameras
        predicted = 0
        offsets = np.arange(-(s.patch_px + s.search_px), s.patch_px + s.search_px + 1, dtype=np.float64)
        gx, gy = np.meshgrid(offsets, offsets)
        size = 2 * s.patch_px + 1
        for index, view in enumerate(site.views):
            o = view.observations
            if len(o.track_ids) == 0:
                continue
            p_cam = view.points_camera(self.rig.wac, self.rig.baseline_m)
            hrc_T_cam = hrc_T_body @ view.body_T_camera
            p_h = p_cam @ hrc_T_cam[:3, :3].T + hrc_T_cam[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv_h = hrc.project(p_h, distort=False)
            inside = ((p_cam[:, 2] > s.min_range_m) & (p_h[:, 2] > s.min_range_m)
                      & (uv_h[:, 0] >= margin) & (uv_h[:, 0] <= hrc.width - 1 - margin)
                      & (uv_h[:, 1] >= margin) & (uv_h[:, 1] <= hrc.height - 1 - margin))
            if not inside.any():  # most views lie outside the frame: no float copy of their image
                continue
            left = view.left.astype(np.float32)
            n = view.body_T_camera[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the body's up, in the camera
            for j in np.flatnonzero(inside):
                track = int(o.track_ids[j])
                if track in seen:
                    continue
                predicted += 1
                u, v = float(o.uvv[j, 0]), float(o.uvv[j, 2])
                template = cv2.getRectSubPix(left, (size, size), (u, v))
                texture = float(template.std())
                if texture < s.min_texture_dn:
                    continue
                # the ground through the point (level in the body frame): its homography WAC -> HRC
                h = k_h @ (hrc_T_cam[:3, :3] + np.outer(hrc_T_cam[:3, 3], n) / float(n @ p_cam[j])) @ wac_k_inv
                grid = np.stack([u + gx, v + gy, np.ones_like(gx)], axis=-1) @ h.T
                map_x = (grid[..., 0] / grid[..., 2]).astype(np.float32)
                map_y = (grid[..., 1] / grid[..., 2]).astype(np.float32)
                synthetic = cv2.remap(blurred, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                score = cv2.matchTemplate(synthetic, template, cv2.TM_CCOEFF_NORMED)
                _, best, _, (bx, by) = cv2.minMaxLoc(score)
                if best < s.min_ncc or not (0 < bx < score.shape[1] - 1 and 0 < by < score.shape[0] - 1):
                    continue
                dx, dy = peak_offset(score, bx, by)
                q = h @ np.array([u + bx - s.search_px + dx, v + by - s.search_px + dy, 1.0])
                seen.add(track)
                ids.append(track)
                uvs.append(q[:2] / q[2])
                views.append(index)
                wac_uvs.append((u, v))
                nccs.append(best)
                textures.append(texture)
                predictions.append(uv_h[j])
                points_cam.append(p_cam[j])
                points_hrc.append(p_h[j])
                hrc_R_cams.append(hrc_T_cam[:3, :3])
        uvs, predictions = np.array(uvs).reshape(-1, 2), np.array(predictions).reshape(-1, 2)
        covariances = self._prediction_covariances(np.array(points_cam).reshape(-1, 3),
                                                   np.array(points_hrc).reshape(-1, 3),
                                                   np.array(hrc_R_cams).reshape(-1, 3, 3))
        shift, agree = frame_agreement(uvs, predictions, covariances, s)
        return HrcMatches(pan_rad, tilt_rad, np.array(ids, dtype=np.int64)[agree], uvs[agree],
                          np.array(views, dtype=int)[agree], np.array(wac_uvs).reshape(-1, 2)[agree], predicted,
                          time.perf_counter() - start, np.array(nccs)[agree], np.array(textures)[agree],
                          shift, int(len(uvs) - agree.sum()))

    def _prediction_covariances(self, points_cam: np.ndarray, points_hrc: np.ndarray, hrc_R_cam: np.ndarray
                                ) -> np.ndarray:
        """(N, 2, 2) HRC px²: how far a correct match may sit from its prediction once the frame's
        shift is removed. The WAC triangulation's error (points_cam in the left WAC, points_hrc the
        same points in the HRC) seen from the HRC, plus `agreement_sigma_px` WAC px either way for
        the feature's and the peak's error."""
        s, hrc = self.settings, self.rig.hrc
        cov_cam = triangulation_covariance(points_cam, self.rig.wac, self.rig.baseline_m, s.agreement_sigma_px)
        x, y, z = points_hrc.T
        projection = np.zeros((len(points_cam), 2, 3))  # d(u, v) / d(x, y, z) of the pinhole
        projection[:, 0, 0], projection[:, 0, 2] = hrc.fx / z, -hrc.fx * x / z**2
        projection[:, 1, 1], projection[:, 1, 2] = hrc.fy / z, -hrc.fy * y / z**2
        jac = projection @ hrc_R_cam
        return jac @ cov_cam @ np.transpose(jac, (0, 2, 1)) + (s.agreement_sigma_px * self.scale) ** 2 * np.eye(2)


def frame_agreement(found: np.ndarray, predicted: np.ndarray, covariances: np.ndarray,
                    settings: HrcSettings) -> tuple[np.ndarray, np.ndarray]:
    """The frame's shift (the median of found - predicted: the mast's pointing error, HRC px) and
    which matches agree with it: found - predicted - shift inside the `agreement_chi2` ellipse of
    the prediction's covariance (N, 2, 2). Fewer than `min_frame_matches` matches give no shift to
    check them by: none agree."""
    shift = np.median(found - predicted, axis=0) if len(found) else np.zeros(2)
    if len(found) < settings.min_frame_matches:
        return shift, np.zeros(len(found), dtype=bool)
    r = found - predicted - shift
    mahalanobis2 = np.einsum("ni,ni->n", r, np.linalg.solve(covariances, r[..., None])[..., 0])
    return shift, mahalanobis2 < settings.agreement_chi2


def hrc_footprints(rig: Rig, views: list[PanoramaView], frames: list[tuple[float, float]],
                   margin_px: int = 10) -> list[list[Region]]:
    """Per panorama view, the rectangles of its left image that the HRC frames at (pan, tilt)
    see: each HRC corner's ray meets the level ground under the rover (between 3 and 100 m;
    100 m above the horizon), projected into the view. The HRC sits 0.4 m from the left WAC,
    so its footprint in the WAC image depends on the range; the ground's range is the one it
    sees."""
    if rig.hrc is None or not frames:
        return [[] for _ in views]
    hrc = rig.hrc
    corners = np.array([[0.0, 0.0], [hrc.width - 1.0, 0.0], [hrc.width - 1.0, hrc.height - 1.0],
                        [0.0, hrc.height - 1.0]])
    rays = np.column_stack([corners, np.ones(4)]) @ np.linalg.inv(hrc.matrix()).T
    points = []  # per frame, its corners' ground points in the body frame
    for pan, tilt in frames:
        body_T_hrc = rig.body_T_hrc(pan, tilt).matrix()
        origin, directions = body_T_hrc[:3, 3], rays @ body_T_hrc[:3, :3].T
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        with np.errstate(divide="ignore"):
            to_ground = np.where(directions[:, 2] < 0, -origin[2] / directions[:, 2], 100.0)
        points.append(origin + np.clip(to_ground, 3.0, 100.0)[:, None] * directions)
    wac = rig.wac
    out = []
    for view in views:
        camera_T_body = np.linalg.inv(view.body_T_camera)
        regions = []
        for p in points:
            q = p @ camera_T_body[:3, :3].T + camera_T_body[:3, 3]
            if np.any(q[:, 2] < 0.5):  # not in front of this view
                continue
            uv = wac.project(q, distort=False)
            x0, y0 = np.floor(uv.min(axis=0)).astype(int) - margin_px
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + margin_px
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, wac.width), min(y1, wac.height)
            if x1 - x0 >= 2 * margin_px and y1 - y0 >= 2 * margin_px:
                regions.append((int(x0), int(y0), int(x1), int(y1)))
        out.append(regions)
    return out
