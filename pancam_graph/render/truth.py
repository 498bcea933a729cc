"""The renderer's truth for measurements made on its images: the terrain point under a
rectified pixel (the depth of a pinhole rendering of the rectified camera at its true pose), and
where that point is in another image. What tie points and matches are checked against."""

from __future__ import annotations

import cv2
import numpy as np

from ..config import Scenario
from ..geometry.rig import Camera
from ..sim.world import dense_path
from .renderer import TerrainRenderer
from .terrain import terrain_tiles


class RenderedTruth:
    """Truth poses (world_T_body per stop) and the terrain of a rendered scenario and seed."""

    def __init__(self, scenario: Scenario, seed: int, world_T_body: np.ndarray, camera: Camera):
        self.renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), seed), seed=seed)
        self.world_T_body = world_T_body
        self.camera = camera
        self._depth: dict[tuple[int, bytes], np.ndarray] = {}

    def world_point(self, stop: int, body_T_camera: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """The terrain point (world, m) seen at rectified pixel uv by the camera at body_T_camera."""
        cam = self.camera
        world_T_camera = self.world_T_body[stop] @ body_T_camera
        key = (stop, body_T_camera.tobytes())
        if key not in self._depth:
            self._depth[key] = self.renderer.render_depth(world_T_camera, cam).astype(np.float32)
        z = float(cv2.getRectSubPix(self._depth[key], (1, 1), (float(uv[0]), float(uv[1])))[0, 0])
        ray = np.array([(uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy, 1.0])
        return world_T_camera[:3, :3] @ (z * ray) + world_T_camera[:3, 3]

    def pixel(self, stop: int, body_T_camera: np.ndarray, world: np.ndarray, camera: Camera | None = None
              ) -> np.ndarray:
        """Where a world point is in the rectified image of the camera at body_T_camera (another
        camera than the rectified WAC's, e.g. the HRC, if given)."""
        camera_T_world = np.linalg.inv(self.world_T_body[stop] @ body_T_camera)
        q = camera_T_world[:3, :3] @ world + camera_T_world[:3, 3]
        return (camera or self.camera).project(q[None], distort=False)[0]

    def transfer_error(self, a: tuple[int, np.ndarray, np.ndarray], b: tuple[int, np.ndarray, np.ndarray],
                       camera_b: Camera | None = None) -> float:
        """Pixel distance between b's measurement and where the terrain under a's measurement is
        in b's image; each of a and b is (stop, body_T_camera, rectified uv); b's camera is
        another than the rectified WAC (the HRC) if given."""
        world = self.world_point(*a)
        return float(np.linalg.norm(self.pixel(b[0], b[1], world, camera_b) - b[2]))
