"""A rendered 3-D control field for calibration: 176 coded targets (ArUco 4x4) on a wall and
two wings folded 35 degrees towards the cameras, photographed by the scenario's stereo pair
(its lens and misalignment, as `render` uses them) from several views. Pixels are ray-cast
through the exact lens model (each pixel undistorted to its ray), the targets evaluated
analytically and averaged over 4 x 4 samples per pixel, then blurred like optics and given
the sensor's noise: the images carry no geometry but the lens's."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..config import Scenario
from ..errors import ResultsError
from ..formats.calibration import write_control_field, write_opencv_yaml
from ..formats.calibration_images import FIELD_FILE, TRUTH_FILE
from ..frontend.calibrate import ARUCO_DICTIONARY, ControlField
from ..geometry.rig import Camera, rig_preset
from ..runtime.processes import cores
from .scenario_images import raw_stereo_pair

PITCH_M = 0.20  # target spacing on a panel
TARGET_M = 0.15  # printed marker side, black border included
SUPERSAMPLES = 4  # per pixel side
WHITE, BLACK, BACKDROP = 205.0, 28.0, 95.0  # DN
OPTICS_BLUR_PX = 0.6


@dataclass(frozen=True)
class Panel:
    """A flat board with `cols` x `rows` targets: its top-left corner, unit axes along its
    rows (a) and down its columns (b), in the field frame (x right, y down, z away from the
    cameras)."""

    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    cols: int
    rows: int
    brightness: float

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.a, self.b)

    @property
    def size_m(self) -> tuple[float, float]:
        return self.cols * PITCH_M, self.rows * PITCH_M


def standard_panels() -> list[Panel]:
    """A 2.0 x 1.6 m wall (80 targets) between two 1.2 x 1.6 m wings (48 each) folded 35 deg
    towards the cameras: 176 targets over 0.7 m of depth."""
    fold = np.deg2rad(35.0)
    down = np.array([0.0, 1.0, 0.0])
    wall = Panel(np.array([-1.0, -0.8, 0.0]), np.array([1.0, 0.0, 0.0]), down, 10, 8, 1.0)
    wing = 6 * PITCH_M
    left_a = np.array([np.cos(fold), 0.0, np.sin(fold)])
    right_a = np.array([np.cos(fold), 0.0, -np.sin(fold)])
    gap = 0.02
    left = Panel(np.array([-1.0 - gap, -0.8, 0.0]) - wing * left_a, left_a, down, 6, 8, 0.85)
    right = Panel(np.array([1.0 + gap, -0.8, 0.0]), right_a, down, 6, 8, 0.9)
    return [wall, left, right]


def control_field(panels: list[Panel]) -> ControlField:
    """The targets' surveyed centres: ids in order, panel by panel, row by row."""
    ids, points, panel_of = [], [], []
    for p, panel in enumerate(panels):
        for r in range(panel.rows):
            for c in range(panel.cols):
                points.append(panel.origin + (c + 0.5) * PITCH_M * panel.a + (r + 0.5) * PITCH_M * panel.b)
                ids.append(len(ids))
                panel_of.append(p)
    return ControlField(np.array(ids), np.array(points), np.array(panel_of))


def view_poses(count: int, seed: int) -> list[np.ndarray]:
    """field_T_left for each view: 3.5-6 m from the field, turned up to 18 deg, rolled up to
    25 deg (roll and depth are what separate the principal point and the focal length)."""
    rng = np.random.default_rng([seed, 7])
    poses = []
    for i in range(count):
        distance = 3.5 + 2.5 * (i % 4) / 3.0
        yaw, pitch = np.deg2rad(rng.uniform(-18, 18)), np.deg2rad(rng.uniform(-10, 10))
        roll = np.deg2rad(rng.uniform(-25, 25))
        rotation = (cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0] @ cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0]
                    @ cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0])
        aim = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), 0.0])
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = aim - distance * rotation[:, 2] - rotation[:, 0] * 0.25  # the pair's centre on the aim
        poses.append(pose)
    return poses


class FieldRenderer:
    """Ray-casts the panels for one camera (its rays computed once, through its lens)."""

    def __init__(self, panels: list[Panel], camera: Camera):
        self.panels = panels
        self.camera = camera
        self.bits = _marker_bits(sum(p.cols * p.rows for p in panels))
        # each panel's normal and axes, three columns a panel: what a ray's direction is multiplied by
        self.panel_axes = np.column_stack([v for panel in panels for v in (panel.normal, panel.a, panel.b)])
        # Each pixel centre (and a ring around the image) undistorted to its ray: 20 fixed-point
        # steps reach 1e-12 px (checked by projecting back), as the rendered geometry must be far
        # finer than what calibration measures. An accuracy test per step would cost x7.
        gu, gv = np.meshgrid(np.arange(-1.0, camera.width + 1.0), np.arange(-1.0, camera.height + 1.0))
        grid = cv2.undistortPoints(np.column_stack([gu.ravel(), gv.ravel()]).reshape(-1, 1, 2), camera.matrix(),
                                   camera.distortion(), None, None, criteria=(cv2.TERM_CRITERIA_COUNT, 20, 0.0))
        grid = grid.reshape(gu.shape + (2,)).astype(np.float32)  # x/z, y/z: 1e-7 relative is 1e-4 px
        # The supersamples' rays bilinear between the pixels': 1.0e-4 px at most from undistorting
        # each sample (the float32 rays' own rounding; tests/frontend/test_calibrate.py), with 16 times
        # fewer undistortions. The samples sit at multiples of 1/8 px, which remap's 1/32-px
        # interpolation table holds exactly.
        s = SUPERSAMPLES
        offsets = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel() + 1.0  # the grid starts at -1
        v = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel() + 1.0
        uu, vv = np.meshgrid(u.astype(np.float32), v.astype(np.float32))
        self.rays = np.column_stack([cv2.remap(grid[..., k], uu, vv, cv2.INTER_LINEAR).ravel() for k in (0, 1)])

    def render(self, field_T_camera: np.ndarray, rng: np.random.Generator, noise_dn: float) -> np.ndarray:
        return expose(self.optical_image(field_T_camera), rng, noise_dn)

    def optical_image(self, field_T_camera: np.ndarray) -> np.ndarray:
        """The image the lens forms (DN, before the sensor's noise and quantization)."""
        value = np.concatenate([self._cast(field_T_camera, self.rays[i:i + 2 ** 19])
                                for i in range(0, len(self.rays), 2 ** 19)])
        s = SUPERSAMPLES
        image = value.reshape(self.camera.height, s, self.camera.width, s).mean(axis=(1, 3))
        return cv2.GaussianBlur(image, (0, 0), OPTICS_BLUR_PX)

    def _cast(self, field_T_camera: np.ndarray, rays: np.ndarray) -> np.ndarray:
        """The intensity each ray sees: the nearest panel it hits, or the backdrop.

        A ray's direction is d = R (x, y, 1); every product of d the panels need (with each
        panel's normal and axes) is one product of the rays with a small matrix, so no direction or
        hit point is formed per ray."""
        rotation, centre = field_T_camera[:3, :3], field_T_camera[:3, 3]
        axes = self.panel_axes
        # d . v for each panel's vectors, a row each (rows are contiguous: the loop reads them whole)
        along = (axes.T @ rotation[:, :2]) @ rays.T.astype(np.float64) + (rotation[:, 2] @ axes)[:, None]
        depth = np.full(len(rays), np.inf)
        value = np.full(len(rays), BACKDROP)
        first = 0
        for k, panel in enumerate(self.panels):
            dn, da, db = along[3 * k], along[3 * k + 1], along[3 * k + 2]
            offset = centre - panel.origin
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -(offset @ panel.normal) / dn
            a, b = offset @ panel.a + s * da, offset @ panel.b + s * db
            w, h = panel.size_m
            on = (s > 0) & (s < depth) & (a >= 0) & (a < w) & (b >= 0) & (b < h)
            depth[on] = s[on]
            value[on] = panel.brightness * _target_intensity(a[on], b[on], panel, self.bits, first)
            first += panel.cols * panel.rows
        return value


def expose(optical: np.ndarray, rng: np.random.Generator, noise_dn: float) -> np.ndarray:
    """The sensor's 8-bit image of an optical image: noise, then quantization."""
    image = optical + rng.normal(0.0, noise_dn, optical.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _marker_bits(count: int) -> np.ndarray:
    """(count, 6, 6) booleans, True where marker i is white (border cells included)."""
    dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY)
    return np.array([cv2.aruco.generateImageMarker(dictionary, i, 6, borderBits=1) > 127 for i in range(count)])


def _target_intensity(a: np.ndarray, b: np.ndarray, panel: Panel, bits: np.ndarray, first: int) -> np.ndarray:
    """The printed board at panel coordinates (a, b) m: a marker's black or white cell, or the
    white gap between markers; the panel's first target is marker `first`."""
    margin = (PITCH_M - TARGET_M) / 2.0
    col, row = np.floor(a / PITCH_M).astype(int), np.floor(b / PITCH_M).astype(int)
    ma, mb = a - col * PITCH_M - margin, b - row * PITCH_M - margin
    inside = (ma >= 0) & (ma < TARGET_M) & (mb >= 0) & (mb < TARGET_M)
    out = np.full(len(a), WHITE)
    cell = TARGET_M / 6.0
    i = first + row[inside] * panel.cols + col[inside]
    white = bits[i, np.minimum((mb[inside] / cell).astype(int), 5), np.minimum((ma[inside] / cell).astype(int), 5)]
    out[inside] = np.where(white, WHITE, BLACK)
    return out


def render_control_field(scenario: Scenario, folder: Path, views: int = 8, seed: int | None = None,
                         progress: Callable[[str, int, int], None] | None = None) -> int:
    """Write `views` stereo pairs of the control field (`views/NN_left.png`, `NN_right.png`), the
    field's surveyed targets (`control_field.csv`) and the pair's true calibration
    (`truth_calibration.yaml`) into `folder`. Returns the number of images."""
    seed = scenario.seed if seed is None else seed
    rig = rig_preset(scenario.rig)
    truth = raw_stereo_pair(rig.wac, rig.baseline_m, scenario.render)
    left_camera, right_camera = truth.cameras()
    left_T_right = np.linalg.inv(np.vstack([np.column_stack([truth.rotation, truth.translation]), [0, 0, 0, 1.0]]))
    panels = standard_panels()
    folder = Path(folder)
    (folder / "views").mkdir(parents=True, exist_ok=True)
    write_control_field(folder / FIELD_FILE, control_field(panels))
    write_opencv_yaml(folder / TRUTH_FILE, truth)
    rng = np.random.default_rng([seed, 8])
    noise = scenario.render.sensor_noise_dn
    # The ray casting is numpy and OpenCV, which let go of the GIL: the views are cast on every
    # core, and exposed (the noise drawn) here in view order, so the images do not depend on it.
    with ThreadPoolExecutor(max_workers=cores()) as pool:
        left, right = pool.map(lambda camera: FieldRenderer(panels, camera), (left_camera, right_camera))
        shots = [shot for i, pose in enumerate(view_poses(views, seed))
                 for shot in ((f"{i:02d}_left.png", left, pose), (f"{i:02d}_right.png", right, pose @ left_T_right))]
        optical = pool.map(lambda shot: shot[1].optical_image(shot[2]), shots)
        for k, ((name, _, _), image) in enumerate(zip(shots, optical, strict=True)):
            path = folder / "views" / name
            if not cv2.imwrite(str(path), expose(image, rng, noise)):
                raise ResultsError(f"{path}: cannot write the image (disk full or no permission?)")
            if progress is not None and k % 2:
                progress("control field", k // 2 + 1, views)
    return 2 * views
