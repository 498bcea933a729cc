"""The renderer (the [render] extra): exact intrinsics, an image folder that the image front-end
and the back-end run on, and bad frames named."""


import numpy as np
import pytest

from pancam_graph.config import Scenario
from pancam_graph.errors import InputError
from pancam_graph.pipeline import run_traverse
from pancam_graph.render.images import render_scenario
from pancam_graph.render.renderer import TerrainRenderer
from pancam_graph.render.terrain import terrain_tiles
from pancam_graph.results import RunOptions
from pancam_graph.sim import simulate
from pancam_graph.sim.world import dense_path
from pancam_graph.sources import image_folder

SCENARIO = Scenario.model_validate({
    "name": "render_strip", "description": "40 m for the renderer tests",
    "origin": {"lat_deg": 39.7392, "lon_deg": -105.145, "h_m": 1705.0},
    "path": {"waypoints": [[0.0, 0.0, 0.0], [25.0, 4.0, 0.5], [45.0, 2.0, 1.0]], "stop_spacing_m": [1.5, 2.0]},
    "sites": {"enabled": False},
})


def test_depth_seen_through_the_rig_intrinsics_is_where_the_terrain_is():
    traverse, truth = simulate(SCENARIO, 0)
    tiles = terrain_tiles(SCENARIO, dense_path(SCENARIO.path), 0)
    camera = traverse.rig.wac
    renderer = TerrainRenderer(tiles, camera)
    world_T_cam = truth.world_T_body[3] @ traverse.body_T_nav().matrix()
    renderer.render(world_T_cam)
    depth = renderer.depth()
    # terrain vertices in view, projected with the pinhole model: the depth buffer there is theirs
    vertices = np.vstack([t.vertices[:, :3] for t in tiles]).astype(float)
    p_cam = (vertices - world_T_cam[:3, 3]) @ world_T_cam[:3, :3]
    near = (p_cam[:, 2] > 4.0) & (p_cam[:, 2] < 30.0)
    uv = camera.project(p_cam[near], distort=False)
    inside = camera.in_image(uv, margin_px=2)
    uv, z = uv[inside], p_cam[near][inside, 2]
    assert len(z) > 1000
    pixel = np.rint(uv).astype(int)
    # a vertex is visible unless something nearer hides it: compare where it is not hidden
    rendered = depth[pixel[:, 1], pixel[:, 0]]
    visible = rendered > z - 0.05 * z
    assert visible.mean() > 0.8
    relative = np.abs(rendered[visible] - z[visible]) / z[visible]
    assert np.median(relative) < 0.002  # half a pixel of rounding at most


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("render") / "strip"
    n = render_scenario(SCENARIO, folder)
    return folder, n


def test_vo_from_rendered_images(rendered):
    folder, n = rendered
    data = image_folder.load(folder)
    assert len(data.traverse.stops) == n > 15
    assert np.median([len(s.stereo) for s in data.traverse.stops]) > 300
    result = run_traverse(data.traverse, data.truth, data.estimator, data.seed, RunOptions(configs=("vo",)),
                          source=data.info)
    vo = result.configurations["vo"]
    # Lucas-Kanade loses (or mis-locks on the repetitive texture) most tracks over a 2 m step at
    # a few stops: measured 3 VO failures here, bridged by dead reckoning. Tracking aided by the
    # predicted motion is the next step (see the notes of issue 13).
    assert vo.bridged_stops <= 3
    assert vo.metrics.relative_closure_pct < 1.0
    assert vo.consistency.anees < 3.0


def test_a_bad_frame_stops_the_run_or_is_skipped_as_asked(rendered, tmp_path):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(rendered[0], folder)
    image = folder / "images" / "000004_right.png"
    image.write_bytes(image.read_bytes()[:5000])  # truncated
    with pytest.raises(InputError, match=r"000004_right.png: truncated PNG"):
        image_folder.load(folder)
    data = image_folder.load(folder, skip_bad_frames=True)
    assert len(data.traverse.stops[4].stereo) == 0 and "stop 4 skipped" in " ".join(data.info.notes)
    shutil.copy(rendered[0] / "images" / "000004_right.png", image)
    (folder / "images" / "000006_left.png").unlink()
    with pytest.raises(InputError, match=r"000006_left.png: missing"):
        image_folder.load(folder)
