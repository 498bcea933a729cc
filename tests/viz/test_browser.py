"""The live web viewer as a user opens it: `run --rerun serve` prints a URL, and a real headless
Chromium (Debian's `chromium`, driven by Playwright) opened on exactly that URL shows the
traverse while the run is still solving. Set PANCAM_GRAPH_VIEWER_SCREENSHOT=FILE.png to keep
the live frame (docs/rerun_viewer.png is one)."""

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from served import serve_run

from pancam_graph.config import dump_scenario, load_scenario, resolve_scenario
from pancam_graph.viz.rerun_scene import COLOURS

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="no headless browser: install Debian's `chromium` "
                       "(./dev.sh test does where apt can)"),
]
# Small: Chromium paints the page in software, and each screenshot of a 1600 x 1000 page came
# 5-8 s apart while the viewer ingested (3-4 s at this size)
VIEWPORT = {"width": 800, "height": 500}
SHOWN = 250  # pixels of a trajectory: a few hundred metres of line at this size
# Software WebGL: the machine has no GPU (and CI neither)
BROWSER_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def _traverse_pixels(png: bytes) -> int:
    """Pixels of the 3-D view (the left 60 % of the page) in a configuration's colour."""
    from io import BytesIO

    from PIL import Image

    image = np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=int)
    view = image[60:-40, : int(image.shape[1] * 0.6)]
    near = [np.abs(view - np.array(rgb)).max(axis=2) < 24 for rgb in COLOURS.values()]
    return int(np.count_nonzero(np.logical_or.reduce(near)))


def test_the_printed_url_shows_the_traverse_live_in_a_headless_browser(tmp_path):
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the [dev] extra")
    out = tmp_path / "res"
    # 50 km of dead reckoning, the time for the page to load and show it while the run goes on
    # (89 s alone on a quiet machine; the page showed the traverse 45 s after the start; under
    # the suite's load the page was once slower than long_traverse's 15 s run). Without landmarks,
    # sites or GPS its URL comes 8 s after the start, mission_traverse's 43 s.
    scenario = load_scenario(resolve_scenario("mission_traverse"))
    drive_only = scenario.model_copy(update={
        "name": "drive_only", "sites": scenario.sites.model_copy(update={"enabled": False}),
        "gps": scenario.gps.model_copy(update={"enabled": False}),
        "terrain": scenario.terrain.model_copy(update={"landmark_density_per_m2": 0.001})})
    path = tmp_path / "drive_only.toml"
    path.write_text(dump_scenario(drive_only), encoding="utf-8")
    run, url = serve_run(str(path), "--configs", "dead_reckoning", "--one-process", "--out", str(out))
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BROWSER_ARGS)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(url)  # exactly what was printed
            start, shown, live = time.monotonic(), 0, None
            while time.monotonic() - start < 600:  # a bound on a wait (a busy machine), not a speed target
                time.sleep(1.0)
                done = (out / "metrics.json").exists()
                png = page.screenshot(timeout=120_000)  # a software-rendered page ingesting is slow
                shown = _traverse_pixels(png)
                if shown > SHOWN:
                    live = not done
                    (tmp_path / "viewer.png").write_bytes(png)
                    target = os.environ.get("PANCAM_GRAPH_VIEWER_SCREENSHOT")
                    if target and live:
                        Path(target).write_bytes(png)
                    break
            # the control: the same page without the recording's address is rerun's welcome screen
            # (the live page closed first: beside it, that screenshot took 35 s)
            page.close()
            bare = browser.new_page(viewport=VIEWPORT)
            bare.goto(url.split("?", 1)[0])
            time.sleep(5.0)
            welcome = _traverse_pixels(bare.screenshot(timeout=120_000))
            browser.close()
        assert shown > SHOWN, f"the viewer showed no trajectory ({shown} pixels); see {tmp_path / 'viewer.png'}"
        assert live, "the traverse showed only after the run had finished: not live"
        assert welcome < SHOWN / 5, welcome
    finally:
        run.kill()
        run.wait()
