"""Images in, stereo observations out: features on the left image, matched into the right image
along the same row (rectified pair), tracked from frame to frame with persistent track ids.

The dissertation's constraints on stereo matches (Chapter 4.2): the same row after rectification,
mutual consistency (left -> right -> left lands where it started), positive disparity within
range, and disparity smoothness over the Delaunay triangulation of the left points (a match
whose disparity disagrees with all its neighbours' is a mismatch, not a depth edge, when it
disagrees by more than `smoothness_px` and `smoothness_fraction`). Matches are sub-pixel
(pyramidal Lucas-Kanade).

Three detectors (`FrontendConfig.detector`):
- `gftt`: Shi-Tomasi corners, stereo and temporal matching by Lucas-Kanade optical flow with a
  forward-backward check (the default: see docs/frontend.md for the comparison), optionally
  found cell by cell (`detection_grid`, as MER's VO picks its corners). Given the
  camera's motion since the last frame (`CameraMotion`, from wheel odometry), each track's
  search starts where its triangulated point reprojects, features on the ground are tracked
  from the previous image warped by the ground's homography (`ground_warp`), and a track
  whose offset from its prediction strays from the others' is dropped;
- `orb`, `sift`: keypoints and descriptors, stereo matching by descriptor along the row,
  temporal matching by descriptor near the previous position, both mutual; the disparity is
  then refined to sub-pixel by Lucas-Kanade.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import Delaunay, cKDTree

from ..config import FrontendConfig
from ..errors import FrontendError
from ..geometry.rig import Camera, triangulate_rectified
from ..records import StereoObservations


@dataclass
class StageTimes:
    """Wall time of each stage for every frame, ms."""

    ms: dict[str, list[float]] = field(default_factory=dict)

    def add(self, stage: str, start: float) -> float:
        now = time.perf_counter()
        self.ms.setdefault(stage, []).append((now - start) * 1e3)
        return now

    def summary(self) -> dict[str, dict[str, float]]:
        return {stage: {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "mean": float(np.mean(v))}
                for stage, v in self.ms.items()}


@dataclass
class _Tracks:
    """The features of the last frame: left pixel positions, track ids, disparities and (for
    descriptor detectors) descriptors."""

    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    disparity: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    descriptors: np.ndarray | None = None


@dataclass(frozen=True)
class CameraMotion:
    """What the rover believes the left camera did since the last frame (wheel odometry, as
    MER's VO uses it): current_T_previous (4x4) of the rectified left camera, and that camera's
    model, to say where each tracked feature should now appear."""

    current_T_previous: np.ndarray
    camera: Camera
    baseline_m: float

    @staticmethod
    def from_body_motion(previous_T_current: np.ndarray, body_T_camera: np.ndarray, camera: Camera,
                         baseline_m: float) -> CameraMotion:
        """From the body's motion (previous_T_current, 4x4) and the camera's mount on the body."""
        camera_motion = np.linalg.inv(body_T_camera) @ previous_T_current @ body_T_camera
        return CameraMotion(np.linalg.inv(camera_motion), camera, baseline_m)

    def ground_homography(self, uv: np.ndarray, disparity: np.ndarray, max_range_m: float,
                          tolerance_m: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The homography that the ground near the camera induces between the previous and the
        current image (previous pixels -> current pixels), and which features lie on it: a plane
        fitted (RANSAC) to the previous frame's triangulated features nearer than `max_range_m`.
        None when too few near features agree on a plane."""
        p = triangulate_rectified(uv[:, 0], uv[:, 0] - disparity, uv[:, 1], self.camera, self.baseline_m)
        near = np.flatnonzero(np.isfinite(p[:, 2]) & (p[:, 2] < max_range_m))
        if len(near) < 20:
            return None
        # RANSAC over 100 planes through three near features at once
        q = p[near]
        a, b, c = q[np.random.default_rng(0).integers(0, len(q), (3, 100))]
        normals = np.cross(b - a, c - a)
        length = np.linalg.norm(normals, axis=1)
        normals, a = normals[length > 1e-9] / length[length > 1e-9, None], a[length > 1e-9]
        if not len(normals):
            return None
        counts = (np.abs(q @ normals.T - np.einsum("ij,ij->i", normals, a)) < tolerance_m).sum(axis=0)
        best = int(np.argmax(counts))
        if counts[best] < 20:
            return None
        inliers = q[np.abs(q @ normals[best] - normals[best] @ a[best]) < tolerance_m]
        # least squares over the plane's inliers: n . X = d with |n| = 1 (the scatter's smallest axis)
        centre = inliers.mean(axis=0)
        normal = np.linalg.eigh((inliers - centre).T @ (inliers - centre))[1][:, 0]
        offset = float(normal @ centre)
        if abs(offset) < 0.3:  # the camera on the plane: no homography
            return None
        on_plane = np.zeros(len(uv), bool)
        on_plane[near] = np.abs(p[near] @ normal - offset) < tolerance_m
        R, t = self.current_T_previous[:3, :3], self.current_T_previous[:3, 3]
        K = self.camera.matrix()
        return K @ (R + np.outer(t, normal) / offset) @ np.linalg.inv(K), on_plane

    def predict(self, uv: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted pixel positions and disparities of features (uv, disparity) of the previous
        frame, and which predictions are usable (in front of the camera)."""
        p = triangulate_rectified(uv[:, 0], uv[:, 0] - disparity, uv[:, 1], self.camera, self.baseline_m)
        q = p @ self.current_T_previous[:3, :3].T + self.current_T_previous[:3, 3]
        ok = np.isfinite(q[:, 2]) & (q[:, 2] > 0.3)
        q[~ok] = (0.0, 0.0, 1.0)  # behind the camera: searched where it was
        predicted = np.where(ok[:, None], self.camera.project(q, distort=False), uv)
        disparity = self.camera.fx * self.baseline_m / q[:, 2]
        return predicted.astype(np.float32), disparity.astype(np.float32), ok


class StereoTracker:
    """Feed it rectified stereo pairs in order; each call returns that frame's observations.
    Given the camera's motion since the last frame, tracks are searched where it says they went."""

    def __init__(self, config: FrontendConfig | None = None):
        self.config = config or FrontendConfig()
        self.times = StageTimes()
        self._last = _Tracks()
        self._previous_left: np.ndarray | None = None
        self._next_id = 0
        # Corner detection runs beside temporal tracking (OpenCV releases the GIL); the worker
        # thread ends with the tracker.
        self._detection = ThreadPoolExecutor(max_workers=1, thread_name_prefix="corners")
        c = self.config
        self._lk = dict(winSize=(c.klt_window_px, c.klt_window_px), maxLevel=c.klt_levels,
                        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        if c.detector == "orb":
            self._features = cv2.ORB_create(nfeatures=c.max_features, scaleFactor=1.2, nlevels=8, fastThreshold=10)
            self._norm = cv2.NORM_HAMMING
        elif c.detector == "sift":
            self._features = cv2.SIFT_create(nfeatures=c.max_features)
            self._norm = cv2.NORM_L2

    def __call__(self, left: np.ndarray, right: np.ndarray, motion: CameraMotion | None = None) -> StereoObservations:
        if left.shape != right.shape or left.ndim != 2:
            raise FrontendError(f"stereo pair: left {left.shape} and right {right.shape} must be equal grayscale "
                                "images")
        start = time.perf_counter()
        if self.config.detector == "gftt":
            uv, ids, disparity = self._klt_frame(left, right, start, motion)
        else:
            uv, ids, disparity = self._descriptor_frame(left, right, start)
        t = time.perf_counter()
        keep = self._smooth(uv, disparity)
        uv, ids, disparity = uv[keep], ids[keep], disparity[keep]
        if self._last.descriptors is not None:
            self._last.descriptors = self._last.descriptors[keep]
        self._last.uv, self._last.ids, self._last.disparity = uv, ids, disparity
        self._previous_left = left
        self.times.add("smoothness", t)
        self.times.ms.setdefault("frame", []).append((time.perf_counter() - start) * 1e3)
        uvv = np.column_stack([uv[:, 0], uv[:, 0] - disparity, uv[:, 1]]).astype(float)
        return StereoObservations(ids.astype(np.int64), uvv)

    # -- corners and optical flow --------------------------------------------------------------

    def _klt_frame(self, left, right, t, motion: CameraMotion | None):
        c = self.config
        uv, ids, disparity = self._last.uv, self._last.ids, self._last.disparity
        # Corners are found on the whole image while the tracks are followed (the two keep both
        # cores busy); those too near a followed track are dropped afterwards.
        corners = self._detection.submit(self._corners, left, c.max_features + len(uv))
        if self._previous_left is not None and len(uv):
            guess = uv
            warp = None
            if motion is not None:
                if c.ground_warp:
                    warp = motion.ground_homography(uv, disparity, c.ground_warp_range_m, c.ground_warp_tolerance_m)
                guess, disparity, _ = motion.predict(uv, disparity)  # disparity: where stereo starts
            if warp is None:
                moved, ok = self.flow(self._previous_left, left, uv, guess)
            else:
                moved, ok = self._flow_over_ground(self._previous_left, left, uv, guess, *warp)
            if motion is not None and ok.sum() > 2:
                # The odometry's heading error moves every track alike; a track that strays from
                # the others' offset has locked onto another texture element.
                offset = moved[ok] - guess[ok]
                stray = np.linalg.norm(offset - np.median(offset, axis=0), axis=1) > c.prediction_gate_px
                ok[np.flatnonzero(ok)[stray]] = False
            uv, ids, disparity = moved[ok], ids[ok], disparity[ok]
        t = self.times.add("temporal", t)
        fresh = self._fresh_corners(left, corners.result(), uv, c.max_features - len(uv))
        uv = np.vstack([uv, fresh]).astype(np.float32)
        ids = np.concatenate([ids, self._new_ids(len(fresh))])
        disparity = np.concatenate([disparity, np.full(len(fresh), np.nan, np.float32)])
        t = self.times.add("detect", t)
        ok, disparity = self._stereo_flow(left, right, uv, disparity)
        self.times.add("stereo", t)
        return uv[ok], ids[ok], disparity[ok]

    def _cells(self, shape: tuple[int, int]) -> list[tuple[int, int, int, int]]:
        """The detection grid's cells (x0, y0, x1, y1), row by row."""
        h, w = shape
        g = self.config.detection_grid
        return [(w * j // g, h * i // g, w * (j + 1) // g, h * (i + 1) // g) for i in range(g) for j in range(g)]

    def _corners(self, image: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Shi-Tomasi corners cell by cell, each cell's strongest first, and each corner's cell.
        The quality threshold is relative to the strongest corner of its own cell, so a
        low-contrast stretch of ground keeps corners beside a field of sharp rocks."""
        c = self.config
        cells = self._cells(image.shape)
        per_cell = -(-count // len(cells))
        found, cell = [np.zeros((0, 2), np.float32)], [np.zeros(0, int)]
        for k, (x0, y0, x1, y1) in enumerate(cells):
            f = cv2.goodFeaturesToTrack(image[y0:y1, x0:x1], per_cell, c.gftt_quality, c.min_distance_px,
                                        blockSize=7)
            if f is not None:
                found.append(f.reshape(-1, 2) + np.float32((x0, y0)))
                cell.append(np.full(len(f), k))
        return np.concatenate(found), np.concatenate(cell)

    def _fresh_corners(self, image, found: tuple[np.ndarray, np.ndarray], tracked: np.ndarray,
                       count: int) -> np.ndarray:
        """`count` corners at least `min_distance_px` from every tracked feature, spread over the
        detection grid: a cell's k-th strongest fresh corner ranks with its tracked features
        counted first, so sparse cells fill up before crowded ones; refined to sub-pixel."""
        c = self.config
        found, cell = found
        if not len(found) or count <= 0:
            return np.zeros((0, 2), np.float32)
        if len(tracked):
            distance, _ = cKDTree(tracked).query(found, distance_upper_bound=c.min_distance_px)
            far = distance > c.min_distance_px  # inf when no track is that near
            found, cell = found[far], cell[far]
        g = c.detection_grid
        h, w = image.shape
        tracked_cell = (np.clip(tracked[:, 1] * g // h, 0, g - 1) * g + np.clip(tracked[:, 0] * g // w, 0, g - 1))
        already = np.bincount(tracked_cell.astype(int), minlength=g * g)
        first = np.searchsorted(cell, np.arange(g * g))  # corners come cell by cell, strongest first
        rank = np.arange(len(found)) - first[cell] + already[cell]
        found = found[np.argsort(rank, kind="stable")[:count]]
        if not len(found):
            return np.zeros((0, 2), np.float32)
        return cv2.cornerSubPix(image, found.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1),
                                (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)).reshape(-1, 2)

    def flow(self, a, b, points, guess, levels: int | None = None, accept=None) -> tuple[np.ndarray, np.ndarray]:
        """Lucas-Kanade from image a to b with a forward-backward check; (positions in b, ok).
        `accept(positions in b)` rejects matches before the check (whose cost is per point)."""
        lk = dict(self._lk)
        if levels is not None:
            lk["maxLevel"] = levels
        p0 = points.reshape(-1, 1, 2).astype(np.float32)
        p1, status, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, guess.reshape(-1, 1, 2).astype(np.float32).copy(),
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        h, w = a.shape
        p1 = p1.reshape(-1, 2)
        ok = (status.ravel() == 1) & (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        if accept is not None:
            ok &= accept(p1)
        check = np.flatnonzero(ok)
        if len(check):
            back, status, _ = cv2.calcOpticalFlowPyrLK(b, a, p1[check].reshape(-1, 1, 2).copy(), p0[check].copy(),
                                                       flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
            ok[check] = (status.ravel() == 1) & (
                np.linalg.norm(back.reshape(-1, 2) - points[check], axis=1) < self.config.mutual_max_px)
        return p1, ok

    def _flow_over_ground(self, previous, current, uv, guess, homography, on_plane):
        """Optical flow with the ground's perspective change taken out: a near ground patch grows
        10-30 % from one stop to the next, which biases translation-only Lucas-Kanade by pixels
        (docs/frontend.md). Features on the ground are tracked from the previous image warped
        into the current view by the ground's homography; the others from the image as it is."""
        moved, ok = np.zeros_like(uv), np.zeros(len(uv), bool)
        rest = ~on_plane
        moved[rest], ok[rest] = self.flow(previous, current, uv[rest], guess[rest])
        h, w = previous.shape
        warped = cv2.warpPerspective(previous, homography, (w, h), flags=cv2.INTER_LINEAR)
        there = cv2.perspectiveTransform(uv[on_plane].reshape(-1, 1, 2).astype(np.float64), homography)
        moved[on_plane], ok[on_plane] = self.flow(warped, current, there.reshape(-1, 2).astype(np.float32),
                                                   guess[on_plane])
        return moved, ok

    def _stereo_flow(self, left, right, uv, disparity) -> tuple[np.ndarray, np.ndarray]:
        """Right-image positions by optical flow from the left, started at the last disparity
        (or at zero for new features); kept when on the same row, mutually consistent and with
        a disparity in range."""
        c = self.config
        start = np.where(np.isfinite(disparity), disparity, c.initial_disparity_px)
        guess = uv - np.column_stack([start, np.zeros(len(uv))]).astype(np.float32)
        matched, ok = self.flow(left, right, uv, guess, accept=lambda right_uv: self.stereo_ok(uv, right_uv))
        return ok, (uv[:, 0] - matched[:, 0]).astype(np.float32)

    def stereo_matches(self, left: np.ndarray, right: np.ndarray, uv: np.ndarray,
                       start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """New left features' right matches as a frame's own are found, the flow started at
        `start` disparities (NaN or None: the configured initial one): (ok, disparity)."""
        start = np.full(len(uv), np.nan, np.float32) if start is None else start.astype(np.float32)
        return self._stereo_flow(left, right, uv.astype(np.float32), start)

    def smooth(self, uv: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """Which stereo matches agree with a Delaunay neighbour's disparity (see `_smooth`)."""
        return self._smooth(uv, disparity)

    def stereo_ok(self, left_uv: np.ndarray, right_uv: np.ndarray) -> np.ndarray:
        """The same row (rectified) and a disparity in range."""
        c = self.config
        d = left_uv[:, 0] - right_uv[:, 0]
        return (np.abs(right_uv[:, 1] - left_uv[:, 1]) <= c.row_max_px) & (d > c.min_disparity_px) & (
            d < c.max_disparity_px)

    # -- keypoints and descriptors --------------------------------------------------------------

    def _descriptor_frame(self, left, right, t):
        c = self.config
        kl, dl = self._features.detectAndCompute(left, None)
        kr, dr = self._features.detectAndCompute(right, None)
        t = self.times.add("detect", t)
        if dl is None or dr is None or not len(kl) or not len(kr):
            self._last.descriptors = np.zeros((0, 1), np.uint8)
            return np.zeros((0, 2), np.float32), np.zeros(0, np.int64), np.zeros(0, np.float32)
        pl = np.array([k.pt for k in kl], np.float32)
        pr = np.array([k.pt for k in kr], np.float32)
        dy = np.abs(pl[:, None, 1] - pr[None, :, 1])
        dx = pl[:, None, 0] - pr[None, :, 0]
        allowed = (dy <= c.row_max_px + 1.0) & (dx > c.min_disparity_px) & (dx < c.max_disparity_px)
        i, j = self._mutual(dl, dr, allowed)
        uv, desc = pl[i], dl[i]
        # sub-pixel disparity: optical flow from the matched position, on the full image
        matched, ok = self.flow(left, right, uv, pr[j], levels=1,
                                 accept=lambda right_uv: self.stereo_ok(uv, right_uv))
        d = uv[:, 0] - matched[:, 0]
        uv, desc, d = uv[ok], desc[ok], d[ok]
        t = self.times.add("stereo", t)
        ids = self._new_ids(len(uv))
        last = self._last
        if last.descriptors is not None and len(last.uv) and len(uv):
            near = np.linalg.norm(uv[:, None, :] - last.uv[None, :, :], axis=2) < c.max_motion_px
            a, b = self._mutual(desc, last.descriptors, near)
            ids[a] = last.ids[b]  # the fresh ids of re-found tracks are never used again
        self.times.add("temporal", t)
        self._last.descriptors = desc
        return uv, ids, d.astype(np.float32)

    def _mutual(self, a: np.ndarray, b: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index pairs (i, j): j is i's best allowed match and i is j's, with Lowe's ratio test."""
        if not len(a) or not len(b):
            return np.zeros(0, int), np.zeros(0, int)
        if self._norm == cv2.NORM_HAMMING:
            bits = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2)
            dist = bits.sum(axis=2).astype(np.float32)
        else:
            dist = np.sqrt(np.maximum((a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2 * a @ b.T, 0.0))
        dist = np.where(allowed, dist, np.inf)
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(a))
        first = dist[rows, best]
        second = np.partition(dist, 1, axis=1)[:, 1] if dist.shape[1] > 1 else np.full(len(a), np.inf)
        back = np.argmin(dist, axis=0)
        ok = np.isfinite(first) & (back[best] == rows) & (first < self.config.ratio * second)
        return rows[ok], best[ok]

    # -- shared ----------------------------------------------------------------------------------

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _smooth(self, uv: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """Disparity smoothness over the Delaunay triangulation of the left points: a match that
        disagrees with every neighbour is a mismatch."""
        keep = np.ones(len(uv), dtype=bool)
        if len(uv) < 4:
            return keep
        c = self.config
        try:
            tri = Delaunay(uv.astype(float))
        except Exception:  # scipy's QhullError for degenerate layouts (all points on a line)
            return keep
        indptr, neighbours = tri.vertex_neighbor_vertices
        owner = np.repeat(np.arange(len(uv)), np.diff(indptr))  # the point each neighbour entry belongs to
        near = disparity[neighbours]
        agrees = np.abs(near - disparity[owner]) <= np.maximum(c.smoothness_px, c.smoothness_fraction * near)
        has_neighbour = np.diff(indptr) > 0
        keep = ~has_neighbour
        np.logical_or.at(keep, owner, agrees)
        return keep
