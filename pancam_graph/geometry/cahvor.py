"""The camera models of NASA's Mars rovers: CAHV (Yakimovsky & Cunningham 1978), CAHVOR (Gennery
2001: radial distortion about an optical axis O) and CAHVORE (Gennery 2006: a moving entrance
pupil, E, and a linearity between perspective and fisheye), as PDS labels give them; and their
conversion to the photogrammetric model the rest of the code uses (a rotation and an OpenCV
pinhole with k1, k2, p1, p2: Di & Li 2004 convert CAHVOR to such a model).

Pixel coordinates are (sample, line) = (x, y), 0 at the centre of the first pixel, as in the
labels and in OpenCV. Vectors are in the model's reference frame (a label's
REFERENCE_COORD_SYSTEM_NAME, e.g. the rover navigation frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .rig import Camera

NEWTON_STEPS = 30
_CONVERGED = 1e-12
# H' and V' of a well-formed model are perpendicular; JPL's models have them within about
# 0.01 deg (the 122 Curiosity Navcam labels: at most 0.003 deg). Beyond this the model is refused.
MAX_HV_SKEW_DEG = 0.5


@dataclass(frozen=True)
class CameraModel:
    """A CAHV, CAHVOR or CAHVORE model. `o` and `r` make it CAHVOR; with `e` it is CAHVORE, whose
    `linearity` is 1 for a perspective lens, 0 for a fisheye (Gennery 2006's "type" and "P")."""

    c: np.ndarray
    a: np.ndarray
    h: np.ndarray
    v: np.ndarray
    o: np.ndarray | None = None
    r: np.ndarray | None = None
    e: np.ndarray | None = None
    linearity: float = 1.0
    name: str = field(default="", compare=False)  # where it came from, for messages

    def __post_init__(self) -> None:
        for key in ("c", "a", "h", "v", "o", "r", "e"):
            value = getattr(self, key)
            if value is not None:
                value = np.asarray(value, dtype=float)
                if value.shape != (3,) or not np.all(np.isfinite(value)):
                    raise InputError(f"{self.name}: camera model {key.upper()} must be 3 finite numbers, got {value}")
                object.__setattr__(self, key, value)
        if (self.o is None) != (self.r is None) or (self.e is not None and self.o is None):
            raise InputError(f"{self.name}: a camera model has O and R together (CAHVOR), and E only with them")
        for key in ("a", "o"):
            value = getattr(self, key)
            if value is not None and abs(np.linalg.norm(value) - 1.0) > 1e-3:
                raise InputError(f"{self.name}: camera model {key.upper()} must be a unit vector, its length is "
                                 f"{np.linalg.norm(value):.4f}")
        if self.o is not None:  # labels round it to 6 digits; CAHVORE's angles need it unit
            object.__setattr__(self, "o", self.o / np.linalg.norm(self.o))
        skew = self.hv_skew_deg
        if not skew <= MAX_HV_SKEW_DEG:
            raise InputError(f"{self.name}: camera model H and V are {90 + skew:.3f} deg apart once A is taken out: "
                             f"expected 90 deg within {MAX_HV_SKEW_DEG} deg")

    @property
    def kind(self) -> str:
        return "CAHV" if self.o is None else "CAHVOR" if self.e is None else "CAHVORE"

    # -- the linear part (CAHV) ------------------------------------------------------------------

    @property
    def hc(self) -> float:
        return float(self.a @ self.h)

    @property
    def vc(self) -> float:
        return float(self.a @ self.v)

    @property
    def hs(self) -> float:
        return float(np.linalg.norm(np.cross(self.a, self.h)))

    @property
    def vs(self) -> float:
        return float(np.linalg.norm(np.cross(self.a, self.v)))

    @property
    def h_unit(self) -> np.ndarray:
        return (self.h - self.hc * self.a) / self.hs

    @property
    def v_unit(self) -> np.ndarray:
        return (self.v - self.vc * self.a) / self.vs

    @property
    def hv_skew_deg(self) -> float:
        """How far H' and V' are from perpendicular, in degrees."""
        return float(abs(np.rad2deg(np.arcsin(np.clip(self.h_unit @ self.v_unit, -1.0, 1.0)))))

    def _cahv(self, p: np.ndarray) -> np.ndarray:
        along = p @ self.a
        return np.column_stack([p @ self.h / along, p @ self.v / along])

    # -- projection ----------------------------------------------------------------------------

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of points (N, 3) in the model's frame (in front of the camera)."""
        p = np.atleast_2d(np.asarray(points, dtype=float)) - self.c
        if self.o is None:
            return self._cahv(p)
        if self.e is None:
            zeta = p @ self.o
            lam = p - zeta[:, None] * self.o
            tau = np.sum(lam * lam, axis=1) / zeta**2
            mu = self.r[0] + self.r[1] * tau + self.r[2] * tau**2
            return self._cahv(p + mu[:, None] * lam)
        return self._cahv(self._cahvore_distorted(p))

    def _cahvore_distorted(self, p: np.ndarray) -> np.ndarray:
        """Gennery (2006): the angle theta off O of the ray from the entrance pupil, which moves
        along O with theta, solved by Newton's method; then its image point at the distorted
        angle chi, as a point the linear CAHV part projects."""
        e0, e1, e2 = self.e
        zeta = p @ self.o
        lam_vec = p - zeta[:, None] * self.o
        lam = np.linalg.norm(lam_vec, axis=1)
        theta = np.arctan2(lam, zeta)
        for _ in range(NEWTON_STEPS):
            cos, sin = np.cos(theta), np.sin(theta)
            t2 = theta * theta
            shift = e0 + e1 * t2 + e2 * t2 * t2
            d_shift = 2.0 * e1 * theta + 4.0 * e2 * t2 * theta
            # f(theta) = zeta sin - lam cos - (theta - sin) shift = 0: the point lies on the ray from
            # the pupil C + s O, s = (theta / sin - 1) shift, at angle theta
            f = zeta * sin - lam * cos - (theta - sin) * shift
            df = zeta * cos + lam * sin - (1.0 - cos) * shift - (theta - sin) * d_shift
            step = f / df
            theta = theta - step
            if np.all(np.abs(step) < _CONVERGED):
                break
        chi = self._chi(theta)
        chi2 = chi * chi
        mu = self.r[0] + self.r[1] * chi2 + self.r[2] * chi2 * chi2
        small = theta < 1e-8
        zetap = np.where(small, zeta, lam / np.where(small, 1.0, chi))
        return zetap[:, None] * self.o + (1.0 + mu)[:, None] * lam_vec

    def _chi(self, theta: np.ndarray) -> np.ndarray:
        """CAHVORE's angle as the lens maps it: tan for a perspective lens (linearity 1), the
        angle itself for a fisheye (0), sin beyond (negative)."""
        lin = self.linearity
        if abs(lin) <= 1e-15:
            return theta
        return (np.sin(lin * theta) if lin < 0 else np.tan(lin * theta)) / lin

    def _theta(self, chi: np.ndarray) -> np.ndarray:
        """The inverse of `_chi`."""
        lin = self.linearity
        if abs(lin) <= 1e-15:
            return chi
        return (np.arcsin(lin * chi) if lin < 0 else np.arctan(lin * chi)) / lin

    def rays(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins (N, 3), unit directions (N, 3)) of the rays through pixels (N, 2): the
        back-projection (for CAHVORE the origin is the entrance pupil, which moves with the ray's
        angle; else C)."""
        uv = np.atleast_2d(np.asarray(pixels, dtype=float))
        f = self.v[None, :] - uv[:, 1:2] * self.a
        g = self.h[None, :] - uv[:, 0:1] * self.a
        ray = np.cross(f, g)
        if np.cross(self.v, self.h) @ self.a < 0:
            ray = -ray
        ray /= np.linalg.norm(ray, axis=1)[:, None]
        origins = np.tile(self.c, (len(uv), 1))
        if self.o is None:
            return origins, ray
        if self.e is None:
            return origins, self._cahvor_undistorted(ray)
        return self._cahvore_rays(uv, ray)

    def _cahvor_undistorted(self, ray: np.ndarray) -> np.ndarray:
        """The true direction of a distorted one: its component across O shrunk by u, where
        (1 + r0) u + r1 tau u^3 + r2 tau^2 u^5 = 1 (Newton's method)."""
        omega = ray @ self.o
        lam = ray - omega[:, None] * self.o
        tau = np.sum(lam * lam, axis=1) / omega**2
        k1, k3, k5 = 1.0 + self.r[0], self.r[1] * tau, self.r[2] * tau * tau
        u = 1.0 - (self.r[0] + k3 + k5)
        for _ in range(NEWTON_STEPS):
            u2 = u * u
            step = (((k5 * u2 + k3) * u2 + k1) * u - 1.0) / ((5.0 * k5 * u2 + 3.0 * k3) * u2 + k1)
            u = u - step
            if np.all(np.abs(step) < _CONVERGED):
                break
        out = ray - (1.0 - u)[:, None] * lam
        return out / np.linalg.norm(out, axis=1)[:, None]

    def _cahvore_rays(self, uv: np.ndarray, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gennery (2006)'s inverse: the distorted angle chi' of the linear ray about O, chi from
        it by Newton's method, theta from chi by the linearity, and the entrance pupil's shift."""
        # the linear ray scaled so that A . ray = 1 (the CAHV ray's point on the unit image plane)
        rp = ray / (ray @ self.a)[:, None]
        zetap = rp @ self.o
        lam_vec = rp - zetap[:, None] * self.o
        chip = np.linalg.norm(lam_vec, axis=1) / zetap
        r0, r1, r2 = self.r
        chi = chip.copy()
        for _ in range(NEWTON_STEPS):
            chi2 = chi * chi
            step = ((1.0 + r0) * chi + r1 * chi2 * chi + r2 * chi2 * chi2 * chi - chip) / \
                (1.0 + r0 + 3.0 * r1 * chi2 + 5.0 * r2 * chi2 * chi2)
            chi = chi - step
            if np.all(np.abs(step) < _CONVERGED):
                break
        theta = self._theta(chi)
        t2 = theta * theta
        small = chip < 1e-8
        sin = np.sin(theta)
        shift = np.where(small, 0.0, (theta / np.where(small, 1.0, sin) - 1.0)
                         * (self.e[0] + self.e[1] * t2 + self.e[2] * t2 * t2))
        across = lam_vec / np.where(small, 1.0, np.linalg.norm(lam_vec, axis=1))[:, None]
        direction = np.where(small[:, None], self.o, sin[:, None] * across + np.cos(theta)[:, None] * self.o)
        return self.c + shift[:, None] * self.o, direction


@dataclass(frozen=True)
class Photogrammetric:
    """A camera model as the rest of the code has it: `model_R_camera` turns camera-frame
    vectors (OpenCV: x right, y down, z forward) into the model's frame, the camera centre is
    the model's C, and `camera` the pinhole with its distortion. `residual_px`: the largest
    difference from the original model's projection over the image (a grid of rays)."""

    model_R_camera: np.ndarray
    centre: np.ndarray
    camera: Camera
    residual_px: float
    rms_px: float

    def project(self, points: np.ndarray) -> np.ndarray:
        p_cam = (np.atleast_2d(points) - self.centre) @ self.model_R_camera
        return self.camera.project(p_cam)


def to_photogrammetric(model: CameraModel, width: int, height: int, grid: int = 25,
                       range_m: float = 10.0) -> Photogrammetric:
    """The rotation and OpenCV pinhole (fx, fy, cx, cy; k1, k2, p1, p2, k3 and the thin prism
    s1..s4, which take up what the tilt of CAHVOR's O from A leaves) that best reproduce
    `model` over a width x height image: CAHV's frame (x along H', z along A) and its focal
    lengths and centre to start, then least squares over a grid x grid of pixels (corners
    included) against the model's own rays (SciPy). A CAHVORE's moving pupil is taken at its
    points `range_m` away."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    xs, ys = np.meshgrid(np.linspace(0.0, width - 1.0, grid), np.linspace(0.0, height - 1.0, grid))
    pixels = np.column_stack([xs.ravel(), ys.ravel()])
    origins, directions = model.rays(pixels)
    points = origins + range_m * directions
    x_axis = model.h_unit
    z_axis = model.a
    y_axis = np.cross(z_axis, x_axis)
    start_R = np.column_stack([x_axis, y_axis / np.linalg.norm(y_axis), z_axis])

    def predicted(params: np.ndarray) -> np.ndarray:
        rotation = start_R @ Rotation.from_rotvec(params[:3]).as_matrix()
        camera = Camera(*params[3:7], width, height, *params[7:])
        return camera.project((points - model.c) @ rotation)

    # the pinhole with radial and tangential terms first, then the rest from there: started
    # together, rotation, centre and the decentering terms can settle in another minimum
    start = np.array([0.0, 0.0, 0.0, model.hs, model.vs, model.hc, model.vc] + [0.0] * 9)
    with np.errstate(all="ignore"):  # rays behind the camera, or none (a distortion too wild): refused below
        usable = np.all(np.isfinite(predicted(start)))
    if not usable:
        raise InputError(f"{model.name}: the camera model gives no ray in front of it for every pixel of its "
                         f"{width} x {height} image: it has no photogrammetric form")
    fit = None
    for free in (11, 16):
        fixed = start[free:]
        fit = least_squares(lambda p, fixed=fixed: (predicted(np.concatenate([p, fixed])) - pixels).ravel(),
                            start[:free], method="lm", xtol=1e-15, ftol=1e-15)
        start = np.concatenate([fit.x, fixed])
    fit.x = start
    error = np.linalg.norm(predicted(fit.x) - pixels, axis=1)
    rotation = start_R @ Rotation.from_rotvec(fit.x[:3]).as_matrix()
    camera = Camera(*fit.x[3:7], width, height, *fit.x[7:])
    return Photogrammetric(rotation, model.c, camera, float(error.max()), float(np.sqrt(np.mean(error**2))))


def from_photogrammetric(camera: Camera, model_R_camera: np.ndarray, centre: np.ndarray,
                         name: str = "") -> CameraModel:
    """The CAHVOR (CAHV without distortion) model of an OpenCV pinhole at `centre` with its axes
    `model_R_camera` in the model's frame. Exact for radial distortion k1, k2: CAHVOR's
    mu = R0 + R1 tau + R2 tau^2 with tau the squared tangent off O scales a ray's offset from O
    as OpenCV's 1 + k1 r^2 + k2 r^4 scales a normalised point's, when O is the optical axis. The
    other terms (k3, tangential, thin prism) have no CAHVOR counterpart and are refused."""
    if any((camera.k3, camera.p1, camera.p2, camera.s1, camera.s2, camera.s3, camera.s4)):
        raise InputError(f"{name or 'camera'}: only radial k1, k2 distortion has a CAHVOR form; k3, p1, p2 and "
                         "s1..s4 must be 0")
    rotation = np.asarray(model_R_camera, dtype=float)
    a = rotation[:, 2]
    h = camera.fx * rotation[:, 0] + camera.cx * a
    v = camera.fy * rotation[:, 1] + camera.cy * a
    if camera.k1 == 0.0 and camera.k2 == 0.0:
        return CameraModel(np.asarray(centre, dtype=float), a, h, v, name=name)
    return CameraModel(np.asarray(centre, dtype=float), a, h, v, a.copy(), np.array([0.0, camera.k1, camera.k2]),
                       name=name)
