"""How far behind a run the browser's web viewer is: `run SCENARIO --rerun serve`, the printed
URL opened in a headless Chromium with software WebGL (no GPU), a screenshot every few seconds,
and the viewer's own "N s latency" and the stop it shows read off each one (tesseract OCR).

    .venv/bin/python scripts/viewer_latency.py [SCENARIO] [--seconds 90] [--out DIR] [-- RUN ARGS]

Needs Debian's `chromium` and `tesseract-ocr`, and playwright (the [dev] extra)."""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from PIL import Image
from playwright.sync_api import sync_playwright

ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def read(image: Image.Image, box: tuple[int, int, int, int]) -> str:
    """OCR of a part of a screenshot, enlarged 3x (the viewer's text is small)."""
    part = image.crop(box)
    part = part.resize((part.width * 3, part.height * 3), Image.LANCZOS)
    return subprocess.run(["tesseract", "-", "-", "--psm", "7"], input=_png(part), capture_output=True).stdout.decode()


def _png(image: Image.Image) -> bytes:
    from io import BytesIO

    buffer = BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenario", nargs="?", default="denver_trail")
    parser.add_argument("--seconds", type=float, default=90.0)
    parser.add_argument("--out", type=Path, default=Path("results/viewer_latency"))
    parser.add_argument("--size", default="1600x1000", help="browser viewport")
    parser.add_argument("run_args", nargs="*")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(args.out / "run", ignore_errors=True)
    exe = Path(sys.executable).parent / "pancam-graph"
    start = time.monotonic()
    run = subprocess.Popen([str(exe), "run", args.scenario, "--out", str(args.out / "run"), "--quiet", "--no-plots",
                            "--rerun", "serve", "--serve-for", str(args.seconds), *args.run_args],
                           stderr=subprocess.PIPE, text=True)
    said = ""
    while "web viewer at" not in said:
        line = run.stderr.readline()
        if not line:
            sys.exit(f"no viewer URL: {said}")
        said += line
    url = said.split("web viewer at ", 1)[1].split()[0]
    print(f"{time.monotonic() - start:5.1f} s  URL printed: {url}")
    width, height = (int(v) for v in args.size.split("x"))
    finished, rows = None, []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=shutil.which("chromium"), args=ARGS)
        page = browser.new_page(viewport={"width": width, "height": height})
        page.goto(url)
        while time.monotonic() - start < args.seconds:
            time.sleep(2.0)
            shot = args.out / f"viewer_{time.monotonic() - start:05.1f}s.png"
            page.screenshot(path=shot, timeout=120_000)
            t = time.monotonic() - start
            if finished is None and (args.out / "run" / "metrics.json").exists():
                finished = t
                print(f"{t:5.1f} s  the run has written its results")
            image = Image.open(shot).convert("RGB")
            latency = re.search(r"([\d.]+)\s*s\s*latency", read(image, (0, 0, 500, 36)))
            stop = re.search(r"#\s*(\d+)", read(image, (width - 110, height - 30, width, height)))
            rows.append((t, latency and float(latency[1]), stop and int(stop[1])))
            print(f"{t:5.1f} s  viewer at stop {stop[1] if stop else '-':>5}, "
                  f"latency {latency[1] + ' s' if latency else '-'}   ({shot.name})")
        browser.close()
    run.terminate()
    during = [r[1] for r in rows if r[1] is not None and (finished is None or r[0] <= finished)]
    last = max((r[2] for r in rows if r[2] is not None), default=None)
    caught = next((r[0] for r in rows if r[2] == last), None)
    print(f"run finished at {finished} s; viewer latency during the run: max {max(during, default=None)} s; "
          f"last stop shown {last}, first shown at {caught} s")


if __name__ == "__main__":
    main()
