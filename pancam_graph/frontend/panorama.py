"""A site's panorama images into stereo features with site-wide tracks.

Every WAC pair of the panorama is matched left to right as the navigation pairs are
(frontend/tracker.py). Neighbouring frames overlap by a few degrees of pan or tilt; a feature
seen in two of them is one track. Pan/tilt-aided matching (the dissertation's eq. 4.3): the mast angles give
the relative orientation of the two frames, so each triangulated feature of one frame is
back-projected into the other, the image is warped by the rotation's homography, and the
feature is searched for by optical flow only near its prediction; it joins the other frame's
feature found there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..config import FrontendConfig
from ..geometry.rig import Camera, triangulate_rectified
from ..records import StereoObservations
from .tracker import StereoTracker

LINK_PX = 1.5  # a flow end point this near the other frame's feature is that feature
FOCUS_FEATURES = 150  # corners looked for in each focus region (an HRC frame's footprint: ~145 x 145 px)

# A region of a view's left image, (x0, y0, x1, y1) pixels, where features are wanted densely.
Region = tuple[int, int, int, int]


@dataclass
class PanoramaView:
    """One rectified WAC pair of a site panorama and its stereo features (site track ids)."""

    pan_rad: float
    tilt_rad: float
    body_T_camera: np.ndarray  # 4x4, the rectified left camera in the body frame
    left: np.ndarray
    right: np.ndarray
    observations: StereoObservations = field(default_factory=StereoObservations.empty)

    def points_camera(self, camera: Camera, baseline_m: float) -> np.ndarray:
        o = self.observations.uvv
        return triangulate_rectified(o[:, 0], o[:, 1], o[:, 2], camera, baseline_m)


@dataclass
class SitePanorama:
    """What a site's panorama gives from images: its views, each with its features."""

    stop: int
    site: int
    views: list[PanoramaView]
    links: int = 0  # features found again in a neighbouring frame (pan/tilt-aided)
    seconds: float = 0.0


class PanoramaMatcher:
    """Features for every frame of a site's panorama, one track per feature seen in overlapping
    frames. Track ids are unique over every site the matcher sees."""

    def __init__(self, camera: Camera, baseline_m: float, config: FrontendConfig | None = None, first_id: int = 0):
        self.camera, self.baseline_m = camera, baseline_m
        self.config = config or FrontendConfig()
        self._next_id = first_id
        self._tracker = StereoTracker(self.config)  # its optical flow (forward-backward checked)

    def new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def __call__(self, stop: int, site: int, views: list[PanoramaView],
                 focus: list[list[Region]] | None = None) -> SitePanorama:
        """`focus`: per view, regions of its left image where features are also looked for on
        their own (the footprints of the site's HRC frames: the frame's strongest corners,
        which the whole image's quality threshold leaves out where the ground is less contrasted
        than elsewhere in the view)."""
        start = time.perf_counter()
        for k, view in enumerate(views):
            found = StereoTracker(self.config)(view.left, view.right)
            uvv = found.uvv
            if focus is not None and focus[k]:
                uvv = self._with_focus(view, uvv, focus[k])
            view.observations = StereoObservations(self.new_ids(len(uvv)), uvv)
        panorama = SitePanorama(stop, site, views)
        panorama.links = self._link_overlaps(views)
        panorama.seconds = time.perf_counter() - start
        return panorama

    def _with_focus(self, view: PanoramaView, uvv: np.ndarray, regions: list[Region]) -> np.ndarray:
        """The view's features and the focus regions' own corners, stereo-matched as the frame's
        were and checked for disparity smoothness with them."""
        c = self.config
        corners = []
        for x0, y0, x1, y1 in regions:
            f = cv2.goodFeaturesToTrack(view.left[y0:y1, x0:x1], FOCUS_FEATURES, c.gftt_quality, c.min_distance_px,
                                        blockSize=7)
            if f is not None:
                corners.append(f.reshape(-1, 2) + np.float32((x0, y0)))
        if not corners:
            return uvv
        fresh = np.concatenate(corners)
        taken = uvv[:, [0, 2]]
        if len(taken):  # not on a feature the frame already has
            distance = np.min(np.linalg.norm(fresh[:, None, :] - taken[None, :, :], axis=2), axis=1)
            fresh = fresh[distance > c.min_distance_px]
        fresh = fresh[_spaced(fresh, c.min_distance_px)]  # regions may overlap
        if not len(fresh):
            return uvv
        fresh = cv2.cornerSubPix(view.left, fresh.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)).reshape(-1, 2)
        # started at the nearest feature's disparity: the ground's is tens of pixels at 10-20 m,
        # past what the flow finds from the default start
        start = None
        if len(taken):
            _, nearest = cKDTree(taken).query(fresh)
            start = (uvv[:, 0] - uvv[:, 1])[nearest]
        ok, disparity = self._tracker.stereo_matches(view.left, view.right, fresh, start)
        fresh, disparity = fresh[ok], disparity[ok]
        uv = np.vstack([taken, fresh])
        d = np.concatenate([uvv[:, 0] - uvv[:, 1], disparity])
        keep = self._tracker.smooth(uv, d)
        keep[: len(uvv)] = True  # the frame's own passed the check among themselves
        new = keep[len(uvv):]
        added = np.column_stack([fresh[new, 0], fresh[new, 0] - disparity[new], fresh[new, 1]])
        return np.vstack([uvv, added])

    # -- pan/tilt-aided matching between overlapping frames ----------------------------------------

    def _link_overlaps(self, views: list[PanoramaView]) -> int:
        parent: dict[int, int] = {}

        def root(t: int) -> int:
            while parent.get(t, t) != t:
                t = parent[t]
            return t

        links = 0
        for i, a in enumerate(views):
            for b in views[i + 1:]:
                for ta, tb in self.overlap_matches(a, b):
                    ra, rb = root(int(ta)), root(int(tb))
                    if ra != rb:
                        parent[max(ra, rb)] = min(ra, rb)
                        links += 1
        if parent:
            # A track appears at most once per frame: a merge that would put one track twice in a
            # frame (two features of one frame joined through others) keeps the first.
            for view in views:
                ids = np.array([root(int(t)) for t in view.observations.track_ids], dtype=np.int64)
                _, first = np.unique(ids, return_index=True)
                keep = np.zeros(len(ids), bool)
                keep[first] = True
                view.observations = StereoObservations(ids[keep], view.observations.uvv[keep])
        return links

    def overlap_matches(self, a: PanoramaView, b: PanoramaView) -> list[tuple[int, int]]:
        """(track in a, track in b) for a's features found in b near where the mast angles put
        them: a's triangulated points back-projected into b, a's image warped into b's view by
        the rotation between them, Lucas-Kanade from the prediction with a forward-backward check."""
        cam = self.camera
        if not len(a.observations) or not len(b.observations):
            return []
        b_T_a = np.linalg.inv(b.body_T_camera) @ a.body_T_camera
        # quick reject: optical axes further apart than the field of view diagonal
        if b_T_a[2, 2] < np.cos(2.0 * np.arctan(np.hypot(cam.width, cam.height) / (2.0 * cam.fx))):
            return []
        p = a.points_camera(cam, self.baseline_m)
        q = p @ b_T_a[:3, :3].T + b_T_a[:3, 3]
        front = q[:, 2] > 0.5
        predicted = np.full((len(q), 2), -1.0)
        predicted[front] = cam.project(q[front], distort=False)
        inside = front & cam.in_image(predicted, margin_px=self.config.klt_window_px)
        if not inside.any():
            return []
        # The frames share (nearly) an optical centre: the rotation's homography warps a's image
        # into b's view, so the flow compares like with like.
        K = cam.matrix()
        H = K @ b_T_a[:3, :3] @ np.linalg.inv(K)
        h, w = a.left.shape
        warped = cv2.warpPerspective(a.left, H, (w, h), flags=cv2.INTER_LINEAR)
        start = cv2.perspectiveTransform(a.observations.uvv[inside][:, [0, 2]].reshape(-1, 1, 2), H).reshape(-1, 2)
        p1, good = self._tracker.flow(warped, b.left, start.astype(np.float32), predicted[inside], levels=1)
        # the feature of b nearest to each flow end point
        b_uv = b.observations.uvv[:, [0, 2]]
        distance, nearest = cKDTree(b_uv).query(p1)
        nearest = np.minimum(nearest, len(b_uv) - 1)  # a flow end point that is no number has none
        good &= distance < LINK_PX
        # and the two frames' disparities agree with one depth (b's is a's point seen from b)
        expected = cam.fx * self.baseline_m / q[inside][:, 2]
        b_disparity = b.observations.uvv[nearest, 0] - b.observations.uvv[nearest, 1]
        good &= np.abs(b_disparity - expected) < np.maximum(2.0, 0.1 * expected)
        a_tracks = a.observations.track_ids[inside]
        return [(int(a_tracks[k]), int(b.observations.track_ids[nearest[k]])) for k in np.flatnonzero(good)]


def unaided_matches(a: PanoramaView, b: PanoramaView, features: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """For comparison with the aided matching: SIFT over both left images, mutual nearest
    neighbours with Lowe's ratio test, kept when a fundamental matrix (RANSAC, 1 px) explains them.
    (uv in a, uv in b)."""
    sift = cv2.SIFT_create(nfeatures=features)
    ka, da = sift.detectAndCompute(a.left, None)
    kb, db = sift.detectAndCompute(b.left, None)
    none = (np.zeros((0, 2)), np.zeros((0, 2)))
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return none
    matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False)
    forward = matcher.knnMatch(da, db, k=2)
    backward = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(db, da, k=1) if m}
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in forward
             if len(m) == 2 and m[0].distance < 0.8 * m[1].distance and backward.get(m[0].trainIdx) == m[0].queryIdx]
    if len(pairs) < 8:
        return none
    pa = np.float32([ka[i].pt for i, _ in pairs])
    pb = np.float32([kb[j].pt for _, j in pairs])
    _, inliers = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999)
    if inliers is None:
        return none
    keep = inliers.ravel() == 1
    return pa[keep].astype(float), pb[keep].astype(float)


def _spaced(points: np.ndarray, min_distance: float) -> np.ndarray:
    """Which points to keep so that none is within `min_distance` of one kept before it."""
    keep = np.ones(len(points), dtype=bool)
    for i in range(len(points)):
        if keep[i]:
            near = np.linalg.norm(points[i + 1:] - points[i], axis=1) <= min_distance
            keep[i + 1:][near] = False
    return keep
