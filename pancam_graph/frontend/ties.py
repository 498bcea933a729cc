"""Tie points between two sites' panoramas, from the images.

The next site sees the ground between the two from the other side, at a grazing angle, tens of
metres away: a patch looks different from each site. What stays the same is the ground seen
from above. For every feature of the earlier site (a) whose ground the later site (b) should
see at a similar range:

1. predict where it is from b, from the relative pose of the two sites and its covariance;
2. resample the ground around it, on the local plane fitted to a's triangulated features, into
   a small orthoimage from each site's image (each cell the mean of the pixels over it, as a
   sensor integrates), the one from b wide enough for the prediction's 3-sigma uncertainty;
3. find a's orthoimage in b's by normalized cross-correlation: a clear, distinct peak is the
   feature's ground in b, and b's pixel follows through the same plane and prediction;
4. match b's pixel into b's right image (the stereo observation);
5. verify all of a site pair's matches together: one rigid motion must carry a's triangulated
   points onto b's (RANSAC, Mahalanobis distance with both triangulation covariances), and it
   must agree with the prediction, within what the stereo pair's calibration leaves uncertain:
   a calibration error biases every range of both sites alike (a turn of the right camera
   about the vertical by 0.01 deg puts 0.3 px into every disparity, +1 % of range at 30 m),
   which no residual shows and which moves the fitted motion by more than a VO prediction's
   sigma over 40 m.

Each verified tie is b's observation of a's track: the back-end's tie gate checks it again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..geometry.calibration_error import pixel_shifts
from ..geometry.rig import Rig, triangulate_rectified, triangulation_covariance
from ..graph import chi2
from ..graph.tie_gate import RelativePose, SitePoint, site_points
from ..orbital.ortho_registration import peak_offset
from .panorama import SitePanorama
from .tracker import StereoTracker

_GATE_3D = chi2.quantile(0.999, 3)
_GATE_6D = chi2.quantile(0.999, 6)


@dataclass(frozen=True)
class TieSettings:
    cell_m: float = 0.06  # orthoimage cell
    half_cells: int = 16  # a's orthoimage is (2 half + 1) cells square (about 2 m)
    samples: int = 4  # per cell and axis, averaged
    min_ncc: float = 0.8
    # A pair verified with fewer than `wanted_ties` ties at min_ncc is verified again with the
    # matches down to relaxed_ncc: the farthest pairs (50 m) see the ground from the most
    # different directions; their correct peaks are the lower ones. One rigid motion still has
    # to explain them all and agree with the prediction.
    relaxed_ncc: float = 0.7
    wanted_ties: int = 9
    distinct: float = 0.1  # the best peak beats any other (4 cells away) by this much
    range_m: tuple[float, float] = (3.0, 35.0)  # from both sites
    range_ratio: float = 2.0  # the farther site sees the ground at most this much farther
    max_search_m: float = 1.5  # on the ground, from the prediction
    min_search_m: float = 0.3
    max_candidates: int = 600
    min_verified: int = 4
    ransac_iterations: int = 300
    match_sigma_px: float = 1.0  # of b's pixel found through the orthoimages (measured on renders)


@dataclass(frozen=True)
class Tie:
    """Site b's stereo observation of site a's track."""

    track: int
    a_view: int
    a_uvv: np.ndarray
    b_view: int
    b_uvv: np.ndarray
    ncc: float


@dataclass(frozen=True)
class _Peak:
    """A's feature found in b's left image by correlation, before its stereo match."""

    track: int
    a_view: int
    a_uvv: np.ndarray
    b_view: int
    uv: np.ndarray
    disparity_guess: float
    ncc: float


@dataclass
class TieResult:
    ties: list[Tie] = field(default_factory=list)
    candidates: int = 0  # a's features predicted in b's images at a similar range
    matches: list[Tie] = field(default_factory=list)  # found by correlation and in b's right image
    seconds: float = 0.0
    note: str = ""


class TieMatcher:
    """`calibration_sigmas`: the stereo pair's calibration error's 1-sigma per term
    (geometry/calibration_error.py's NAMES), when the estimator estimates it; None when it
    trusts the calibration."""

    def __init__(self, rig: Rig, sigma_px: float, settings: TieSettings | None = None,
                 calibration_sigmas: np.ndarray | None = None):
        self.rig, self.camera, self.baseline_m = rig, rig.wac, rig.baseline_m
        self.sigma_px = sigma_px
        self.calibration_sigmas = None if calibration_sigmas is None else np.asarray(calibration_sigmas, float)
        self.s = settings or TieSettings()
        self._tracker = StereoTracker()  # its stereo optical flow

    def __call__(self, a: SitePanorama, b: SitePanorama, prediction: RelativePose) -> TieResult:
        start = time.perf_counter()
        result = TieResult()
        points = self._site_points(a)
        ground = _Ground(points)
        candidates = self._candidates(a, b, points, prediction)
        result.candidates = len(candidates)
        peaks = [self._match(a, b, track, a_view, a_index, b_view, radius_m, points[track].p_body, ground,
                             prediction) for track, a_view, a_index, b_view, radius_m in candidates]
        found = self._stereo(b, [peak for peak in peaks if peak is not None])
        strong = [m for m in found if m.ncc >= self.s.min_ncc]
        result.matches = strong
        result.ties = self.verify(strong, points, a, b, prediction, result)
        if len(result.ties) < self.s.wanted_ties and len(found) > len(strong):
            relaxed = TieResult()
            relaxed.ties = self.verify(found, points, a, b, prediction, relaxed)
            if len(relaxed.ties) > len(result.ties):
                result.note = (f"{len(strong)} matches of NCC {self.s.min_ncc} or more verified {len(result.ties)} "
                               f"ties; all {len(found)} down to {self.s.relaxed_ncc} verified {len(relaxed.ties)}")
                result.matches, result.ties = found, relaxed.ties
        result.seconds = time.perf_counter() - start
        return result

    # -- prediction --------------------------------------------------------------------------------

    def _site_points(self, site: SitePanorama) -> dict[int, SitePoint]:
        views: dict[int, list] = {}
        for view in site.views:
            mount = gtsam.Pose3(view.body_T_camera)
            for track, uvv in zip(view.observations.track_ids, view.observations.uvv, strict=True):
                views.setdefault(int(track), []).append((mount, uvv))
        return {t: p for t, p in site_points(views, self.rig, self.sigma_px).items() if p is not None}

    def _candidates(self, a: SitePanorama, b: SitePanorama, points: dict[int, SitePoint], prediction: RelativePose):
        """(track, a view, index in it, b view, search radius m) for a's features whose ground b
        sees at a similar range, each in the b view where it lies farthest from the border."""
        s, cam = self.s, self.camera
        margin = 2.0 * s.half_cells + 8.0  # px: room for the orthoimage's footprint, roughly
        picked, seen = [], set()  # one a view per track: the first that sees it
        for a_view, view in enumerate(a.views):
            for index, track in enumerate(view.observations.track_ids.tolist()):
                if track in points and track not in seen:
                    seen.add(track)
                    picked.append((track, a_view, index))
        if not picked:
            return []
        tracks = np.array([r[0] for r in picked])
        p_a = np.array([points[int(t)].p_body for t in tracks])
        range_a = np.linalg.norm(p_a - np.array([a.views[r[1]].body_T_camera[:3, 3] for r in picked]), axis=1)
        # each point in b's frame, and its uncertainty there: the relative pose's and a's triangulation's
        # (not the calibration's: widening the search by it lost half of the ties of rendered
        # short_trail seed 1, drawn 1.3 sigma off, to ambiguous peaks and the search's limit)
        # Pose3.transformTo for all at once: q = R^T (p - t), d q / d pose = [skew(q), -I] (GTSAM's
        # [rotation, translation] tangent), d q / d p = R^T
        rotation, shift = prediction.a_T_b.rotation().matrix(), prediction.a_T_b.translation()
        p_b = (p_a - shift) @ rotation
        h_pose = np.zeros((len(p_b), 3, 6))
        h_pose[:, :, :3] = _skews(p_b)
        h_pose[:, :, 3:] = -np.eye(3)
        cov_body = np.array([points[int(t)].cov_body for t in tracks])
        cov = h_pose @ prediction.covariance @ np.transpose(h_pose, (0, 2, 1)) + rotation.T @ cov_body @ rotation
        radius = 3.0 * np.sqrt(np.maximum(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1], 0.0))
        radius = np.clip(radius, s.min_search_m, None)
        best_view = np.full(len(p_b), -1)
        best_room = np.zeros(len(p_b))
        for b_view, view in enumerate(b.views):
            cam_T_b = np.linalg.inv(view.body_T_camera)
            q = p_b @ cam_T_b[:3, :3].T + cam_T_b[:3, 3]
            in_front = q[:, 2] > 0.5
            uv = np.full((len(q), 2), -1e9)
            uv[in_front] = cam.project(q[in_front], distort=False)
            room = np.minimum.reduce([uv[:, 0], cam.width - 1 - uv[:, 0], uv[:, 1], cam.height - 1 - uv[:, 1]])
            range_b = np.linalg.norm(q, axis=1)
            ok = (in_front & (room > margin) & (range_b >= s.range_m[0]) & (range_b <= s.range_m[1])
                  & (np.maximum(range_a, range_b) <= s.range_ratio * np.minimum(range_a, range_b)))
            better = ok & (room > best_room)
            best_view[better], best_room[better] = b_view, room[better]
        usable = (best_view >= 0) & (range_a >= s.range_m[0]) & (range_a <= s.range_m[1]) & (radius <= s.max_search_m)
        order = np.flatnonzero(usable)
        if len(order) > s.max_candidates:  # the nearest ground first: it is seen best
            order = order[np.argsort(range_a[order])[:s.max_candidates]]
        return [(int(tracks[k]), picked[k][1], picked[k][2], int(best_view[k]), float(radius[k])) for k in order]

    # -- matching ------------------------------------------------------------------------------------

    def _match(self, a: SitePanorama, b: SitePanorama, track, a_view, a_index, b_view, radius_m, p_a, ground,
               prediction: RelativePose) -> _Peak | None:
        s = self.s
        va, vb = a.views[a_view], b.views[b_view]
        # The orthoimages are laid on the ground where a's ray meets its neighbours' plane, not at
        # a's own triangulation: there the features matched best were those whose disparity error
        # cancelled the pair's calibration error, and the ties kept a's disparities without the
        # calibration's shift (rendered short_trail seeds 1, 3, 5: the matches' a side +0.23,
        # -0.29, -0.24 px off the drawn pair, against -0.04 to +0.00 for all of a's features;
        # laid on the plane: -0.00, -0.08, -0.13).
        p_a = ground.where_ray_meets(va.body_T_camera[:3, 3], p_a)
        normal = ground.normal(p_a)
        e1 = _cross(normal, np.array([0.0, 1.0, 0.0]))
        if np.linalg.norm(e1) < 0.1:
            e1 = _cross(normal, np.array([1.0, 0.0, 0.0]))
        e1 /= np.linalg.norm(e1)
        e2 = _cross(normal, e1)
        search = int(np.ceil(radius_m / s.cell_m))
        camera_b_in_a = prediction.a_T_b.matrix() @ vb.body_T_camera
        template = self._ortho(va.left, va.body_T_camera, p_a, e1, e2, s.half_cells)
        window = self._ortho(vb.left, camera_b_in_a, p_a, e1, e2, s.half_cells + search)
        if template is None or window is None:
            return None
        score = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (x, y) = cv2.minMaxLoc(score)
        if best < s.relaxed_ncc or x in (0, score.shape[1] - 1) or y in (0, score.shape[0] - 1):
            return None  # too weak, or on the search window's edge: the match may lie beyond it
        others = score.copy()
        others[max(0, y - 4):y + 5, max(0, x - 4):x + 5] = -1.0
        if others.size and others.max() > best - s.distinct:
            return None
        dx, dy = peak_offset(score, x, y)
        on_ground = p_a + ((x + dx - search) * e1 + (y + dy - search) * e2) * s.cell_m
        q = np.linalg.inv(camera_b_in_a) @ np.append(on_ground, 1.0)
        uv = self.camera.project(q[:3][None], distort=False)[0]
        return _Peak(track, a_view, va.observations.uvv[a_index].copy(), b_view, uv,
                     self.camera.fx * self.baseline_m / q[2], float(best))

    def _ortho(self, image, frame_T_camera, centre, e1, e2, half):
        """The ground plane (through centre, spanned by e1, e2; frame coordinates) resampled
        from the image of a camera at frame_T_camera: (2 half + 1)^2 cells, each the mean of
        samples^2 pixels; None when it leaves the image."""
        s, cam = self.s, self.camera
        n = 2 * half + 1
        # sample (i, j) of the grid lies at x = step i + first along e1, y = step j + first along
        # e2, and in the camera at R (centre + x e1 + y e2) + t: a plane, so the pixels are a
        # homography of (i, j), warped as one (OpenCV rounds the positions to 1/32 px as remap does)
        step = s.cell_m / s.samples
        first = (0.5 - half * s.samples - 0.5 * s.samples) * step
        camera_T = np.linalg.inv(frame_T_camera)
        rotation, shift = camera_T[:3, :3], camera_T[:3, 3]
        a1, a2 = rotation @ e1, rotation @ e2
        plane = np.column_stack([step * a1, step * a2, rotation @ centre + shift + first * (a1 + a2)])
        last = n * s.samples - 1
        corners = plane @ np.array([[0, last, 0, last], [0, 0, last, last], [1, 1, 1, 1]], float)
        if corners[2].min() <= 0.5:  # the depth is linear over the grid: least at a corner
            return None
        u = cam.fx * corners[0] / corners[2] + cam.cx  # and so are the pixels' extremes
        v = cam.fy * corners[1] / corners[2] + cam.cy
        if u.min() < 0 or v.min() < 0 or u.max() > cam.width - 1 or v.max() > cam.height - 1:
            return None
        fine = cv2.warpPerspective(image, cam.matrix() @ plane, (last + 1, last + 1),
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP).astype(np.float32)
        return cv2.resize(fine, (n, n), interpolation=cv2.INTER_AREA)

    def _stereo(self, b: SitePanorama, peaks: list[_Peak]) -> list[Tie]:
        """The peaks found in b's right images, in their order: the tracker's stereo optical flow
        (same row, disparity in range, forward-backward checked) from the predicted disparity.
        One flow call per view: Lucas-Kanade follows each point on its own, so the columns are
        those of one call per point, at a fraction of the calls' fixed cost."""
        right_u = np.full(len(peaks), np.nan)
        views = np.array([peak.b_view for peak in peaks], int)
        for b_view in np.unique(views):
            index = np.flatnonzero(views == b_view)
            left = np.float32([peaks[k].uv for k in index])
            shift = np.zeros((len(index), 2), np.float32)
            shift[:, 0] = [peaks[k].disparity_guess for k in index]
            view = b.views[int(b_view)]
            right, ok = self._tracker.flow(view.left, view.right, left, left - shift, levels=2,
                                           accept=lambda right_uv, left=left: self._tracker.stereo_ok(left, right_uv))
            right_u[index[ok]] = right[ok, 0]
        return [Tie(peak.track, peak.a_view, peak.a_uvv, peak.b_view, np.array([peak.uv[0], float(u), peak.uv[1]]),
                    peak.ncc) for peak, u in zip(peaks, right_u, strict=True) if np.isfinite(u)]

    # -- verification --------------------------------------------------------------------------------

    def verify(self, found: list[Tie], points: dict[int, SitePoint], a: SitePanorama, b: SitePanorama,
                prediction: RelativePose, result: TieResult | None = None) -> list[Tie]:
        """The matches one rigid motion b_T_a explains (RANSAC over three-point Kabsch fits,
        Mahalanobis inliers), when that motion agrees with the prediction; why not in
        `result.note`."""
        result = TieResult() if result is None else result
        s, cam = self.s, self.camera
        if len(found) < s.min_verified:
            result.note = f"{len(found)} matches, fewer than {s.min_verified}"
            return []
        p = np.array([points[t.track].p_body for t in found])
        cov_p = np.array([points[t.track].cov_body for t in found])
        b_uvv = np.array([t.b_uvv for t in found])
        q_cam = triangulate_rectified(b_uvv[:, 0], b_uvv[:, 1], b_uvv[:, 2], cam, self.baseline_m)
        mounts = np.array([b.views[t.b_view].body_T_camera for t in found])
        q = np.einsum("nij,nj->ni", mounts[:, :3, :3], q_cam) + mounts[:, :3, 3]
        cov_q_cam = triangulation_covariance(q_cam, cam, self.baseline_m, max(s.match_sigma_px, self.sigma_px))
        cov_q = mounts[:, :3, :3] @ cov_q_cam @ np.transpose(mounts[:, :3, :3], (0, 2, 1))
        rng = np.random.default_rng(0)
        best = np.zeros(len(found), bool)
        for _ in range(s.ransac_iterations):
            pick = rng.choice(len(found), 3, replace=False)
            motion = _kabsch(p[pick], q[pick])
            if motion is None:
                continue
            inliers = _inliers(motion, p, cov_p, q, cov_q)
            if inliers.sum() > best.sum():
                best = inliers
        if best.sum() < s.min_verified:
            result.note = f"no rigid motion explains {s.min_verified} of {len(found)} matches"
            return []
        motion, _ = _refine(_kabsch(p[best], q[best]), p[best], cov_p[best], q[best], cov_q[best])
        best = _inliers(motion, p, cov_p, q, cov_q)
        if best.sum() < s.min_verified:
            result.note = f"no rigid motion explains {s.min_verified} of {len(found)} matches"
            return []
        motion, fit = _refine(motion, p[best], cov_p[best], q[best], cov_q[best])
        # The fitted motion against the prediction, each with its covariance (left perturbations
        # of b_T_a: the prediction's right one of a_T_b, negated; to first order their difference
        # is the fit's error plus the prediction's). The points' errors are not all independent:
        # the fit's covariance is scaled by its residuals' variance factor, and the calibration's
        # uncertainty, which biases both sites' points alike and the VO steps between them, is
        # added through the difference's sensitivity to it.
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(motion).compose(prediction.a_T_b))
        fit *= max(1.0, _variance_factor(motion, p[best], cov_p[best], q[best], cov_q[best]))
        covariance = prediction.covariance + fit
        if self.calibration_sigmas is not None:
            chosen = [t for t, ok in zip(found, best, strict=True) if ok]
            sensitivity = self._calibration_sensitivity(chosen, motion, p[best], cov_p[best], cov_q[best], a, b)
            if prediction.calibration_sensitivity is not None:
                sensitivity = sensitivity + prediction.calibration_sensitivity
            covariance = covariance + sensitivity @ np.diag(self.calibration_sigmas**2) @ sensitivity.T
        if xi @ np.linalg.solve(covariance, xi) > _GATE_6D:
            result.note = "the matches' rigid motion disagrees with the prediction"
            return []
        return [t for t, ok in zip(found, best, strict=True) if ok]

    def _calibration_sensitivity(self, ties: list[Tie], motion, p, cov_p, cov_q, a: SitePanorama,
                                 b: SitePanorama) -> np.ndarray:
        """d (fitted b_T_a, left perturbation) / d (calibration error) (6 x 6), by finite
        differences: each term moves both sites' pixels (pixel_shifts), their points are
        triangulated again, and the motion refitted."""
        cam, baseline = self.camera, self.baseline_m

        def points_of(site: SitePanorama, views: list[int], uvv: np.ndarray) -> np.ndarray:
            mounts = np.array([site.views[v].body_T_camera for v in views])
            in_camera = triangulate_rectified(uvv[:, 0], uvv[:, 1], uvv[:, 2], cam, baseline)
            return np.einsum("nij,nj->ni", mounts[:, :3, :3], in_camera) + mounts[:, :3, 3]

        a_views, b_views = [t.a_view for t in ties], [t.b_view for t in ties]
        a_uvv, b_uvv = np.array([t.a_uvv for t in ties]), np.array([t.b_uvv for t in ties])
        a_shifts, b_shifts = (pixel_shifts(uvv, cam.fx, cam.cx, cam.cy) for uvv in (a_uvv, b_uvv))
        a_points = points_of(a, a_views, a_uvv)  # p is a's merged triangulation: moved by this one's change
        inverse = gtsam.Pose3(motion).inverse()
        sensitivity = np.zeros((6, a_shifts.shape[-1]))
        step = _CALIBRATION_STEP
        for term in range(sensitivity.shape[1]):
            moved_p = p + points_of(a, a_views, a_uvv + step * a_shifts[:, :, term]) - a_points
            moved_q = points_of(b, b_views, b_uvv + step * b_shifts[:, :, term])  # verify's q, from b_uvv alone
            refitted, _ = _refine(motion, moved_p, cov_p, moved_q, cov_q, iterations=2)
            sensitivity[:, term] = gtsam.Pose3.Logmap(gtsam.Pose3(refitted).compose(inverse)) / step
        return sensitivity


# finite-difference step of every calibration term (rad or ratio): a tenth of a pixel's shift or
# less, where the fit is linear in it
_CALIBRATION_STEP = 1e-4


class _Ground:
    """The local ground plane around a point, from a site's triangulated features."""

    def __init__(self, points: dict[int, SitePoint], radius_m: float = 2.0):
        self.p = np.array([pt.p_body for pt in points.values()]) if points else np.zeros((0, 3))
        self.tree = cKDTree(self.p[:, :2]) if len(self.p) else None
        self.radius_m = radius_m

    def where_ray_meets(self, origin: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Where the ray from origin through `at` meets the plane of the features around `at`
        (itself left out); `at` where they are too few or steep, or the ray runs along them."""
        plane = self._plane(at, leave_out=True)
        if plane is None:
            return at
        centre, normal = plane
        direction = at - origin
        along = float(normal @ direction)
        if abs(along) < 1e-3 * np.linalg.norm(direction):
            return at
        return origin + direction * float(normal @ (centre - origin)) / along

    def normal(self, at: np.ndarray) -> np.ndarray:
        plane = self._plane(at)
        return np.array([0.0, 0.0, 1.0]) if plane is None else plane[1]

    def _plane(self, at: np.ndarray, leave_out: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """(centroid, upward unit normal) of the features within radius_m of `at` horizontally
        (`at` itself left out if asked); None where they are fewer than 6 or steeper than 25 deg
        (a rock, not the ground)."""
        if self.tree is None:
            return None
        near = self.p[self.tree.query_ball_point(at[:2], self.radius_m)]
        if leave_out:
            near = near[np.linalg.norm(near - at, axis=1) > 1e-9]
        if len(near) < 6:
            return None
        centre = near.mean(axis=0)
        _, _, vt = np.linalg.svd(near - centre, full_matrices=False)  # U (n x n) unused
        normal = vt[2] * np.sign(vt[2][2])
        return (centre, normal) if normal[2] > 0.9 else None


def _kabsch(p: np.ndarray, q: np.ndarray) -> np.ndarray | None:
    """The rigid motion (4x4) taking points p onto q, least squares."""
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    u, sv, vt = np.linalg.svd((p - cp).T @ (q - cq))
    if sv[1] < 1e-9:
        return None
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = r, cq - r @ cp
    return motion


def _refine(motion, p, cov_p, q, cov_q, iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares (Gauss-Newton) of the rigid motion taking p onto q, each residual
    weighted by its covariance; the motion and its covariance (left perturbation, [rotation,
    translation])."""
    for _ in range(iterations):
        r = motion[:3, :3]
        moved = p @ r.T + motion[:3, 3]
        weights = np.linalg.inv(r @ cov_p @ r.T + cov_q)
        jac = np.zeros((len(p), 3, 6))
        jac[:, :, :3] = -_skews(moved)
        jac[:, :, 3:] = np.eye(3)
        jt_w = np.transpose(jac, (0, 2, 1)) @ weights
        information = (jt_w @ jac).sum(axis=0) + 1e-12 * np.eye(6)
        step = np.linalg.solve(information, np.einsum("nij,nj->i", jt_w, q - moved))
        motion = gtsam.Pose3.Expmap(step).matrix() @ motion
    return motion, np.linalg.inv(information)


def _variance_factor(motion, p, cov_p, q, cov_q) -> float:
    """Sum of squared Mahalanobis residuals over the degrees of freedom (3 per point, 6 fitted)."""
    return float(_mahalanobis2(motion, p, cov_p, q, cov_q).sum() / max(3 * len(p) - 6, 1))


def _mahalanobis2(motion, p, cov_p, q, cov_q) -> np.ndarray:
    r = motion[:3, :3]
    diff = q - (p @ r.T + motion[:3, 3])
    cov = r @ cov_p @ r.T + cov_q
    return np.einsum("ni,ni->n", diff, np.linalg.solve(cov, diff[..., None])[..., 0])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross of two 3-vectors, the same sums, without its axis handling (a tenth of its time)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _skews(x: np.ndarray) -> np.ndarray:
    """The cross-product matrix [x]x of each row of x (n x 3): (n, 3, 3)."""
    out = np.zeros((len(x), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -x[:, 2], x[:, 1], -x[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = x[:, 2], -x[:, 1], x[:, 0]
    return out


def _inliers(motion, p, cov_p, q, cov_q) -> np.ndarray:
    return _mahalanobis2(motion, p, cov_p, q, cov_q) <= _GATE_3D
