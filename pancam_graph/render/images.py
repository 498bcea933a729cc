"""A scenario rendered as an image folder: the navigation stereo pair at every stop as PNG
images, with the traverse's timing, GPS, odometry and (in its own files) the truth."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import Scenario
from ..io.observations import write_observations
from ..sim import simulate
from ..sim.world import dense_path
from .renderer import TerrainRenderer, sensor_image
from .terrain import terrain_tiles


def render_scenario(scenario: Scenario, folder: Path, seed: int | None = None,
                    progress: Callable[[str, int, int], None] | None = None) -> int:
    """Write the image folder; returns the number of stops."""
    import cv2

    seed = scenario.seed if seed is None else seed
    traverse, truth = simulate(scenario, seed)
    if progress is not None:
        progress("terrain", 0, 1)
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), seed), traverse.rig.wac, seed=seed)
    body_T_left = traverse.body_T_nav().matrix()
    left_T_right = np.eye(4)
    left_T_right[0, 3] = traverse.rig.baseline_m
    rng = np.random.default_rng([seed, 3])
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, world_T_body in enumerate(truth.world_T_body):
        world_T_left = world_T_body @ body_T_left
        names = (f"images/{k:06d}_left.png", f"images/{k:06d}_right.png")
        for name, pose in zip(names, (world_T_left, world_T_left @ left_T_right), strict=True):
            cv2.imwrite(str(folder / name), sensor_image(renderer.render(pose), rng))
        frames.append(names)
        if progress is not None:
            progress("rendering", k + 1, len(truth.world_T_body))
    write_observations(folder, traverse, scenario.estimator, seed, truth, scenario.rig, frames=frames)
    return len(frames)
