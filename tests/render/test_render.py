"""The renderer (the [render] extra): exact intrinsics, a lens and a misaligned pair that
rectification undoes, an image folder that the image front-end and the back-end run on, and
bad frames named with nothing tracked lost. Site panoramas in the image folder:
tests/frontend/test_site_ties.py, on its rendered strip."""


import cv2
import numpy as np
import pytest

from pancam_graph.config import Scenario, SimulationErrors
from pancam_graph.errors import FrameError, FrontendError, InputError
from pancam_graph.geometry.rig import rig_preset
from pancam_graph.render.renderer import TerrainRenderer, sensor_image
from pancam_graph.render.scenario_images import raw_stereo_pair, render_scenario
from pancam_graph.render.terrain import terrain_tiles
from pancam_graph.sim import simulate
from pancam_graph.sim.world import dense_path
from pancam_graph.solve.pipeline import run
from pancam_graph.solve.results import RunOptions
from pancam_graph.sources import image_folder
from pancam_graph.store.observation_folder import read_observations

pytestmark = [pytest.mark.render, pytest.mark.slow]

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
    renderer = TerrainRenderer(tiles)
    world_T_cam = truth.world_T_body[3] @ traverse.body_T_nav().matrix()
    renderer.render_pinhole(world_T_cam, camera)
    depth = renderer.depth()
    # the unshaded depth pass (the truth of tie points and matches) draws the very same depth
    np.testing.assert_array_equal(renderer.render_depth(world_T_cam, camera), depth)
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


def _shift_px(a: np.ndarray, b: np.ndarray) -> float:
    """Sub-pixel translation between two images of the same view (phase correlation)."""
    import cv2

    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64), window)
    return float(np.hypot(dx, dy))


def test_rectifying_the_raw_pair_gives_the_pinhole_images_of_the_rectified_pair():
    """The lens (Katwijk PanCam emulator distortion, corners move ~17 px) and the right camera's
    focal, principal point and pointing errors are undone by OpenCV rectification with the
    calibration the renderer writes, and the rectified camera frame is the rig's
    (raw_R_rectified): the same view rendered directly through the rectified pinhole pair."""
    traverse, truth = simulate(SCENARIO, 0)
    renderer = TerrainRenderer(terrain_tiles(SCENARIO, dense_path(SCENARIO.path), 0))
    calibration = raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m, SCENARIO.render)
    rectified = calibration.rectified()
    assert not calibration.is_rectified
    left_raw, right_raw = calibration.cameras()
    world_T_left = truth.world_T_body[5] @ traverse.body_T_nav().matrix()
    world_T_right = world_T_left @ calibration.left_T_right()
    raw = (renderer.render(world_T_left, left_raw), renderer.render(world_T_right, right_raw))
    rect_left, rect_right = calibration.rectification_maps()(*raw)
    world_T_rect = world_T_left.copy()
    world_T_rect[:3, :3] = world_T_left[:3, :3] @ rectified.raw_R_rectified
    left_T_right = np.eye(4)
    left_T_right[0, 3] = rectified.baseline_m
    direct_left = renderer.render_pinhole(world_T_rect, rectified.camera)
    direct_right = renderer.render_pinhole(world_T_rect @ left_T_right, rectified.camera)
    ground = slice(600, 1000)  # near ground, full of texture
    for rect, direct in ((rect_left, direct_left), (rect_right, direct_right)):
        assert _shift_px(rect[ground], direct[ground]) < 0.1
        assert np.corrcoef(rect[ground].ravel(), direct[ground].ravel())[0, 1] > 0.95
    # and the raw image really is distorted: without the lens model it is pixels off
    assert _shift_px(raw[1][ground], direct_right[ground]) > 1.0


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("render") / "strip"
    n = render_scenario(SCENARIO, folder)
    return folder, n


def test_vo_from_rendered_images(rendered):
    folder, n = rendered
    data = image_folder.load(folder)
    assert 2 * len(data.traverse.stops) == n > 30  # images: a stereo pair per stop
    assert data.estimator.vo_error_model == "pixel_noise" and data.estimator.vo_rotation_floor_deg_per_m == 0.0
    assert np.median([len(s.stereo) for s in data.traverse.stops]) > 300
    result = run(data.traverse, data.truth, data.estimator, data.seed, RunOptions(configs=("vo",)),
                          source=data.info)
    vo = result.configurations["vo"]
    # Searching each track where the wheel odometry says it went keeps every 2 m step: measured
    # 0 VO failures and 0.08 % closure (0.12 % without the ground warp; 5 failures and 0.29 %
    # without the prediction, where Lucas-Kanade loses or mis-locks most tracks on the
    # repetitive texture). ANEES 0.14 with white pixel noise alone (under-confident on 40 m,
    # where the drawn start pose weighs most).
    assert vo.bridged_stops <= 1
    assert vo.metrics.relative_closure_pct < 0.5
    assert vo.consistency.anees < 3.0


def test_the_rendered_pairs_as_pds4_products_give_the_image_folders_estimates(rendered, tmp_path):
    """render's PDS4 products (CAHVOR cameras, onboard poses in site frames) run through the PDS
    source to the image folder's VO estimates: the same tracks and motions. A label gives no pixel
    sigma, so the folder's is set to the PDS source's for the comparison (it sets the RANSAC
    threshold: at the folder's 0.3 px the estimates differ by centimetres)."""
    from dataclasses import replace

    from pancam_graph.render.pds_products import write_pds4_products
    from pancam_graph.sources import pds

    folder, n = rendered
    assert write_pds4_products(folder, tmp_path / "pds4", 1.7e9) == n
    products = pds.load(tmp_path / "pds4")
    assert set(products.estimator.configurations) == {"onboard", "vo"}
    assert products.info.georeferenced is False  # an Earth scenario: no MSLICE file
    images = image_folder.load(folder)
    images = replace(images, traverse=replace(images.traverse, image_noise_px=products.traverse.image_noise_px))
    np.testing.assert_allclose(products.traverse.rig.wac.matrix(), images.traverse.rig.wac.matrix(), atol=1e-6)
    np.testing.assert_allclose(products.traverse.body_T_nav().matrix(), images.traverse.body_T_nav().matrix(),
                               atol=1e-9)
    for a, b in zip(products.traverse.stops, images.traverse.stops, strict=True):
        np.testing.assert_array_equal(a.stereo.track_ids, b.stereo.track_ids)
        np.testing.assert_allclose(a.stereo.uvv, b.stereo.uvv, atol=1e-6)
    options = RunOptions(configs=("vo",))
    ours = run(products.traverse, None, products.estimator, 0, options, source=products.info)
    theirs = run(images.traverse, images.truth, images.estimator, images.seed, options, source=images.info)
    difference = np.abs(ours.configurations["vo"].world_T_body - theirs.configurations["vo"].world_T_body)
    assert difference.max() < 1e-6  # measured: 0 on the 320 m mars_excerpt leg's 216 stops


def test_a_bad_frame_stops_the_run_or_is_skipped_as_asked(rendered, tmp_path):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(rendered[0], folder)
    image = folder / "images" / "000004_right.png"
    image.write_bytes(image.read_bytes()[:5000])  # truncated
    with pytest.raises(FrameError, match=r"stop 4: .*000004_right.png: truncated PNG") as stopped:
        image_folder.load(folder)
    # what was tracked before the bad frame is handed back, with its truth
    partial = stopped.value.partial
    assert len(partial.traverse.stops) == 4 and len(partial.truth.world_T_body) == 4
    assert all(len(s.stereo) > 300 for s in partial.traverse.stops[1:])
    data = image_folder.load(folder, skip_bad_frames=True)
    assert len(data.traverse.stops[4].stereo) == 0 and "stop 4 skipped" in " ".join(data.info.notes)
    shutil.copy(rendered[0] / "images" / "000004_right.png", image)
    (folder / "images" / "000006_left.png").unlink()
    with pytest.raises(InputError, match=r"000006_left.png: missing"):
        image_folder.load(folder)


def test_the_run_keeps_the_front_ends_work_when_a_frame_stops_it(rendered, tmp_path):
    import shutil

    from typer.testing import CliRunner

    from pancam_graph.cli import app

    folder = tmp_path / "copy"
    shutil.copytree(rendered[0], folder)
    (folder / "images" / "000007_left.png").write_bytes(b"not a png")
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(folder), "--out", str(out), "--quiet", "--configs", "vo"])
    assert result.exit_code == 2
    assert "000007_left.png" in result.output and "stops 0-6 are kept" in result.output
    kept = tmp_path / "run.partial" / "observations"
    assert not out.exists() and (kept / "stereo.csv").is_file()
    assert len(read_observations(kept).traverse.stops) == 7
    again = CliRunner().invoke(app, ["run", str(kept), "--out", str(tmp_path / "kept"), "--quiet", "--configs", "vo"])
    assert again.exit_code == 0, again.output


def test_bench_frontend_times_the_runs_own_loop_on_rendered_images(rendered):
    import json

    from typer.testing import CliRunner

    from pancam_graph.cli import app

    folder, n = rendered
    result = CliRunner().invoke(app, ["bench", "frontend", str(folder)])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output[result.output.index("{"):])
    assert report["frames"] == n // 2 and report["image_size"] == [1024, 1024]
    # raw images: rectification is timed inside each frame, as in `run`
    assert set(report["stages_ms"]) == {"rectify", "temporal", "detect", "stereo", "smoothness"}
    assert report["frame_ms"]["median"] > report["stages_ms"]["rectify"]["median"] > 0
    assert report["features_per_frame_median"] > 300


def test_a_rendered_mars_scenario_has_the_craters_and_its_map_is_of_the_rendered_ground():
    from pancam_graph.config import load_scenario, resolve_scenario
    from pancam_graph.kinds.orbital import BIAS_NAMES
    from pancam_graph.orbital.maps import MapBias
    from pancam_graph.render.scenario_images import maps_of_rendered_ground
    from pancam_graph.render.terrain import Ground

    mars = load_scenario(resolve_scenario("mars_traverse"))
    path_cfg = mars.path.model_copy(update={"waypoints": [[0.0, 0.0, 0.0], [120.0, 5.0, 1.0]], "sharp_turns": []})
    scenario = mars.model_copy(update={"path": path_cfg, "terrain": mars.terrain.model_copy(update={"featureless": []}),
                                       "orbital": mars.orbital.model_copy(update={"orthoimage_pixel_m": 0.0})})
    ground = Ground(scenario, dense_path(scenario.path), 2)
    craters = ground.craters
    big = np.argmax(craters.radii)
    far = np.linalg.norm(ground.tree.query(craters.centres[[big]])[0])
    assert far > 10.0 or craters.radii[big] < 3.0  # off the path, where the relief is not flattened
    bowl, rim = ground.height(craters.centres[[big]]), ground.height(craters.centres[[big]] + [craters.radii[big], 0])
    assert (rim - bowl)[0] > 0.1 * craters.radii[big]  # a bowl 0.2 radii deep (less the undulation)
    traverse, truth = maps_of_rendered_ground(scenario, *simulate(scenario, 2), 2)
    dtm = traverse.measurements["orbital"][0].dtm
    bias = np.array([truth.kinds["orbital"][f"map0_{n}"] for n in BIAS_NAMES])
    rng = np.random.default_rng(0)
    ground_xy = truth.positions[rng.integers(0, len(truth.positions), 200), :2] + rng.uniform(-30, 30, (200, 2))
    shown = np.column_stack([MapBias(bias[0], bias[1], bias[3]).to_map(ground_xy), ground.height(ground_xy)])
    frame = traverse.origin
    error = dtm.at(frame.to_map(shown)) - bias[2] - frame.to_geodetic(shown)[:, 2]
    assert np.sqrt(np.mean(error**2)) < 0.25  # the DTM's 0.1 m error and smoothing of 1.5 m craters


def test_dense_stereo_on_a_rendered_raw_pair_puts_the_points_on_the_ground():
    """SGBM on a raw pair rectified with its calibration: the triangulated points, taken into
    the world through the rig's rectified camera, lie on the rendered ground out to 40 m; and
    the elevation map keeps one point per 0.5 m cell, the one of median height."""

    from pancam_graph.frontend.dense_stereo import dense_points, elevation_map, ground_patch
    from pancam_graph.frontend.panorama import PanoramaView
    from pancam_graph.render.terrain import Ground

    traverse, truth = simulate(SCENARIO, 0)
    renderer = TerrainRenderer(terrain_tiles(SCENARIO, dense_path(SCENARIO.path), 0))
    calibration = raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m, SCENARIO.render)
    stereo = calibration.rectified()
    rig = stereo.of(traverse.rig)
    left_raw, right_raw = calibration.cameras()
    world_T_body = truth.world_T_body[2]
    mounted = traverse.rig.body_T_left(0.0, np.deg2rad(-15.0)).matrix()
    world_T_left = world_T_body @ mounted
    rng = np.random.default_rng(0)
    raw = [sensor_image(renderer.render(world_T, camera), rng) for world_T, camera in
           ((world_T_left, left_raw), (world_T_left @ calibration.left_T_right(), right_raw))]
    pair = calibration.rectification_maps()(*raw)
    points = dense_points(*pair, rig.wac, rig.baseline_m)
    assert len(points) > 2000 and points[:, 2].max() > 25.0
    world_T_camera = world_T_body @ rig.body_T_left(0.0, np.deg2rad(-15.0)).matrix()
    world = points @ world_T_camera[:3, :3].T + world_T_camera[:3, 3]
    height, _, _ = Ground(SCENARIO, dense_path(SCENARIO.path), 0).at(world[:, :2])
    error = world[:, 2] - height
    far = points[:, 2] > 15.0
    assert abs(np.median(error)) < 0.01 and np.percentile(np.abs(error), 90) < 0.05  # measured: 3 mm, 1.7 cm
    assert far.sum() > 200 and abs(np.median(error[far])) < 0.04  # measured: 1.5 cm
    with pytest.raises(FrontendError, match="8-bit grey images"):
        dense_points(pair[0].astype(float), pair[1], rig.wac, rig.baseline_m)

    # the ground patch's two passes (a quarter resolution within 8 m, half beyond) put their cells
    # on the ground, near and far (measured: median -4 mm and -11 mm, 90 % within 1.6 and 4.8 cm)
    view = PanoramaView(0.0, np.deg2rad(-15.0), rig.body_T_left(0.0, np.deg2rad(-15.0)).matrix(), *pair)
    patch = ground_patch([view], rig.wac, rig.baseline_m)
    cells = patch.points_body.astype(float) @ world_T_body[:3, :3].T + world_T_body[:3, 3]
    cell_error = cells[:, 2] - Ground(SCENARIO, dense_path(SCENARIO.path), 0).at(cells[:, :2])[0]
    ahead = np.linalg.norm(patch.points_body[:, :2], axis=1)
    for band, median_m, p90_m in ((ahead < 8.0, 0.01, 0.03), (ahead > 8.0, 0.025, 0.08)):
        assert band.sum() > 100
        assert abs(np.median(cell_error[band])) < median_m and np.percentile(np.abs(cell_error[band]), 90) < p90_m
    with pytest.raises(FrontendError, match="8-bit grey images"):
        ground_patch([PanoramaView(0.0, 0.0, np.eye(4), pair[0].astype(float), pair[1])], rig.wac, rig.baseline_m)
    kept, covariances = elevation_map(points, np.zeros((len(points), 3, 3)))
    cells = np.floor(kept[:, :2] / 0.5)
    assert len(np.unique(cells, axis=0)) == len(kept) < len(points)
    assert len(covariances) == len(kept)


def test_a_sites_ground_from_its_rendered_panorama_is_found_in_the_rendered_orthoimage():
    """The orthoimage rendered from above under the orbiter's sun, through the map's drawn
    bias; a site's ground patch from its rendered, rectified panorama correlated with it from a
    predicted pose 2 m and 0.3 deg off: the rover's east and north in the map's frame within
    0.5 m (measured: 0.32 m, 2.0 of chi-square), and within 3.5 sigma of the correlation's own covariance."""

    import gtsam

    from pancam_graph.config import load_scenario, resolve_scenario
    from pancam_graph.frontend.dense_stereo import ground_patch
    from pancam_graph.frontend.panorama import PanoramaView
    from pancam_graph.kinds.orbital import BIAS_NAMES, _map_pose, predicted_measurement
    from pancam_graph.orbital.ortho_registration import register_patch
    from pancam_graph.render.scenario_images import maps_of_rendered_ground

    mars = load_scenario(resolve_scenario("mars_excerpt"))
    path = mars.path.model_copy(update={"waypoints": [[0.0, 0.0, 0.0], [120.0, 5.0, 1.0]], "sharp_turns": []})
    scenario = mars.model_copy(update={"path": path, "terrain": mars.terrain.model_copy(update={"featureless": []})})
    seed = 5
    renderer = TerrainRenderer(terrain_tiles(scenario, dense_path(scenario.path), seed), seed=seed)
    traverse, truth = maps_of_rendered_ground(scenario, *simulate(scenario, seed), seed, renderer)
    ortho = traverse.measurements["orbital"][0].orthoimage
    assert ortho.values.dtype == np.uint8 and ortho.post_m == 0.5
    seen = ortho.values > 0
    assert 0.2 < seen.mean() < 0.95  # the rendered corridor, and none beyond it
    assert 60 < np.median(ortho.values[seen]) < 200

    calibration = raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m, scenario.render)
    stereo = calibration.rectified()
    rig = stereo.of(traverse.rig)
    left_raw, right_raw = calibration.cameras()
    rectify = calibration.rectification_maps()
    stop = next(s for s in traverse.stops if s.is_site and s.index > 0)
    world_T_body = truth.world_T_body[stop.index]
    rng = np.random.default_rng(1)
    views = []
    for f in stop.panorama:
        world_T_left = world_T_body @ traverse.rig.body_T_left(f.pan_rad, f.tilt_rad).matrix()
        raw = [sensor_image(renderer.render(world_T, camera), rng) for world_T, camera in
               ((world_T_left, left_raw), (world_T_left @ calibration.left_T_right(), right_raw))]
        views.append(PanoramaView(f.pan_rad, f.tilt_rad, rig.body_T_left(f.pan_rad, f.tilt_rad).matrix(),
                                  *rectify(*raw)))
    patch = ground_patch(views, rig.wac, rig.baseline_m)
    assert len(patch.grey) > 5000 and np.abs(patch.points_body[:, :2]).max() < 41.0

    bias = np.array([truth.kinds["orbital"][f"map0_{n}"] for n in BIAS_NAMES])
    pose = gtsam.Pose3(world_T_body)
    guess = _map_pose(pose, bias)
    guess[:2, 3] += [1.6, -1.2]
    guess[:3, :3] = gtsam.Rot3.Yaw(np.deg2rad(0.3)).matrix() @ guess[:3, :3]
    found = register_patch(patch, guess, ortho, traverse.origin, 6.0)
    error = found.measurement - predicted_measurement(pose, bias)[:2]
    assert np.hypot(*error) < 0.5, error
    assert error @ np.linalg.solve(found.covariance, error) < 3.5**2, (error, found.covariance)
    assert found.peak > 0.2 and found.margin > 0.05


def test_the_pair_is_rendered_with_the_calibration_error_the_truth_holds(tmp_path):
    """Under [errors], the right camera is rendered turned by the drawn calibration error, which
    the folder's calibration does not say and its truth does: rectified with that calibration,
    the pair's features stand f times the turn about x apart vertically (measured 5.9 and 6.2 px
    for 6.15), against none for the pair rendered exact; the left images are the same."""
    import tomllib

    errors = SimulationErrors.model_validate({"boresight_sigma_deg": 0.2})  # pixels, not tenths of one
    for name, scenario in (("exact", SCENARIO), ("turned", SCENARIO.model_copy(update={"errors": errors}))):
        render_scenario(scenario, tmp_path / name)
    truth = tomllib.loads((tmp_path / "turned" / "truth.toml").read_text())["kinds"]["stereo_calibration"]
    rig = rig_preset(SCENARIO.rig)
    expected = rig.wac.fx * truth["right_rotation_x_rad"]
    assert abs(expected) > 2.0
    rectify = raw_stereo_pair(rig.wac, rig.baseline_m, SCENARIO.render).rectification_maps()

    def vertical_disparity(name: str, stop: int) -> float:
        raw = [cv2.imread(str(tmp_path / name / "images" / f"{stop:06d}_{side}.png"), cv2.IMREAD_GRAYSCALE)
               for side in ("left", "right")]
        left, right = rectify(*raw)
        corners = cv2.goodFeaturesToTrack(left, 400, 0.01, 10)
        found, status, _ = cv2.calcOpticalFlowPyrLK(left, right, corners, None, winSize=(21, 21), maxLevel=4)
        return float(np.median((found - corners).reshape(-1, 2)[status.ravel() == 1, 1]))

    for stop in (3, 10):
        assert abs(vertical_disparity("exact", stop)) < 0.2
        assert abs(vertical_disparity("turned", stop) - expected) < 0.1 * abs(expected)
        left = [cv2.imread(str(tmp_path / name / "images" / f"{stop:06d}_left.png")) for name in ("exact", "turned")]
        np.testing.assert_array_equal(*left)
