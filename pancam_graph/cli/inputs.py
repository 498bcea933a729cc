"""The commands that make and inspect inputs: track (images -> observation folder), render,
calibrate, simulate, show-config, scenarios."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape
from rich.table import Table

from ..config import SourceOptions
from .app import app, console, user_input
from .common import examples, load_named_scenario, with_progress, with_source_options

if TYPE_CHECKING:  # the heavy imports wait until a command needs them: --help stays fast
    from ..frontend.calibrate import StereoFit
    from ..geometry.stereo_pair import StereoCalibration


@app.command("track", epilog=examples(
    "pancam-graph track ../shared/data/real/kitti_odometry_51 --out obs/",
    "pancam-graph run obs/",
))
@with_source_options("detector", "skip_bad_frames")
def track_command(
    source: str = typer.Argument(..., help="stereo images: a KITTI odometry sequence folder"),
    out: Path = typer.Option(..., "--out", help="observation folder to write (docs/observation_format.md)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    source_options: SourceOptions = SourceOptions(),
) -> None:
    """Run the image front-end and write what it found as an observation folder, so the back-end
    can be run again (`pancam-graph run OUT`) without the images."""
    from .. import api

    with user_input():
        traverse = with_progress(Path(source).name, quiet, lambda report: api.track(
            source, out, detector=source_options.detector,
            skip_bad_frames=bool(source_options.skip_bad_frames), progress=report))
    frames = [len(s.stereo) for s in traverse.stops]
    console.print(f"{len(frames)} frames, median {sorted(frames)[len(frames) // 2]} features per frame; "
                  f"observations in {out}")


@app.command("render", epilog=examples(
    "pancam-graph render short_trail --out images/",
    "pancam-graph render mars_excerpt --out images/ --pds4 products/",
))
def render_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or a scenario TOML file"),
    out: Path = typer.Option(..., "--out", help="image folder to write (keep it out of git)"),
    seed: int | None = typer.Option(None, "--seed", min=0, help="override the scenario's seed"),
    control_field: bool = typer.Option(False, "--control-field", help="render the calibration control field "
                                       "instead, for `pancam-graph calibrate`"),
    views: int = typer.Option(8, "--views", min=3, max=100, help="with --control-field: stereo pairs to take"),
    pds4: Path | None = typer.Option(None, "--pds4", help="also write the navigation pairs into this folder as "
                                     "PDS4 rover products (CAHVOR cameras, onboard poses in site frames), which "
                                     "`run` reads as a rover's"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    errors: str | None = typer.Option(None, "--errors", help=SourceOptions.help("errors")),
) -> None:
    """Render a scenario's navigation stereo pairs and site panoramas (terrain with relief, rocks,
    texture at several scales, shading; the rig's intrinsics through a distorting lens on a
    slightly misaligned pair, with its calibration; sensor noise) into an image folder that `run`
    and `track` read; the truth goes in its own files. The scenario's [render] table sets the
    lens, the pair's errors, rocks and panoramas; its [errors] profile, as in `run`, turns the pair
    off the calibration it writes and the mast off its readings (`--errors ideal`: neither).
    Needs the [render] extra (moderngl on EGL).
    With --control-field: the same pair photographs a 3-D control field of 176 coded targets
    from several views (views/NN_left.png, NN_right.png, control_field.csv, and the pair's true
    calibration in truth_calibration.yaml)."""
    from ..api import check_out
    from ..errors import ConfigError

    with user_input():
        check_out(out)
        if pds4 is not None:
            if control_field:
                raise ConfigError("--pds4 writes a traverse's navigation pairs: not with --control-field")
            check_out(pds4, "--pds4")
        sc = load_named_scenario(scenario, errors)
        start = time.perf_counter()
        if control_field:
            from ..render.control_field import render_control_field

            n = with_progress(sc.name, quiet, lambda report: render_control_field(sc, out, views, seed, report))
        else:
            from ..render.scenario_images import render_scenario

            n = with_progress(sc.name, quiet, lambda report: render_scenario(sc, out, seed, report))
            if pds4 is not None:
                from ..render.pds_products import scenario_start_utc_s, write_pds4_products

                products = with_progress(sc.name, quiet, lambda report: write_pds4_products(
                    out, pds4, scenario_start_utc_s(sc), report))
    console.print(f"{n} images rendered into {out} in {time.perf_counter() - start:.0f} s")
    if pds4 is not None:
        console.print(f"{products} PDS4 products of its navigation pairs in {pds4}")


@app.command("calibrate", epilog=examples(
    "pancam-graph render denver_trail --control-field --out field/",
    "pancam-graph calibrate field/ --out calib.yaml",
))
def calibrate_command(
    folder: Path = typer.Argument(..., help="control-field stereo pairs NAME_left.png / NAME_right.png (any depth)"),
    out: Path = typer.Option(..., "--out", help="OpenCV YAML to write: K1 D1 K2 D2 R T and the rectification "
                             "(R1 R2 P1 P2 Q), which `run` and `track` read as a calibration"),
    field: Path | None = typer.Option(None, "--field", help="the field's targets (target_id,panel,x_m,y_m,z_m); "
                                      "default FOLDER/control_field.csv"),
    truth: Path | None = typer.Option(None, "--truth", help="a calibration to compare with (default "
                                      "FOLDER/truth_calibration.yaml when there is one)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Calibrate a stereo pair from images of a 3-D control field (the dissertation's section 4.2): each
    camera's focal lengths, principal point and k1, k2, p1, p2, then the pair's boresight, and
    the rectification; prints the fit, its uncertainty and, given a truth, the errors."""
    from .. import api

    with user_input():
        outcome = with_progress(folder.name, quiet,
                                lambda report: api.calibrate(folder, out, field=field, truth=truth, progress=report))
    _print_calibration(outcome.fit, outcome.reference, outcome.reference_path)
    console.print(f"calibration written to {outcome.out}")


def _print_calibration(fit: StereoFit, reference: StereoCalibration | None, truth_path: Path | None) -> None:
    import cv2
    import numpy as np

    c = fit.calibration
    table = Table(title=f"{fit.views} views, {fit.left.targets} / {fit.right.targets} targets (left / right)",
                  box=None, padding=(0, 1))
    table.add_column("")
    columns = []

    def parameters(camera) -> list[float]:
        return [camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2, camera.p1, camera.p2]

    truths = reference.cameras() if reference is not None else (None, None)
    for name, camera, camera_fit, truth in zip(("left", "right"), c.cameras(), (fit.left, fit.right), truths,
                                              strict=True):
        table.add_column(name, justify="right")
        table.add_column("1 sigma", justify="right")
        columns += [parameters(camera), list(camera_fit.sigma[:8])]
        if truth is not None:
            table.add_column("- truth", justify="right")
            columns.append([a - b for a, b in zip(parameters(camera), parameters(truth), strict=True)])
    for row, label in enumerate(("fx px", "fy px", "cx px", "cy px", "k1", "k2", "p1", "p2")):
        fmt = "{:.2f}" if row < 4 else "{:.5f}"
        table.add_row(label, *(fmt.format(col[row]) for col in columns))
    extra = [""] * (len(columns) // 2 - 1)
    table.add_row("RMS px", f"{fit.left.rms_px:.3f}", *extra, f"{fit.right.rms_px:.3f}", *extra)
    table.add_row("dropped", str(fit.left.rejected), *extra, str(fit.right.rejected), *extra)
    console.print(table)
    rectified = c.rectified()
    line = (f"baseline {c.baseline_m * 1000:.2f} mm, stereo RMS {fit.stereo_rms_px:.3f} px; rectified focal length "
            f"{rectified.camera.fx:.2f} px")
    if reference is not None:
        angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(c.rotation @ reference.rotation.T)[0]))
        line += (f"\nagainst {truth_path}: baseline {(c.baseline_m - reference.baseline_m) * 1000:+.3f} mm, "
                 f"boresight {angle:.4f} deg, focal lengths {100 * (c.k_left[0, 0] / reference.k_left[0, 0] - 1):+.3f} "
                 f"/ {100 * (c.k_right[0, 0] / reference.k_right[0, 0] - 1):+.3f} %")
    console.print(line)


@app.command("show-config", epilog=examples(
    "pancam-graph show-config mars_traverse > my_traverse.toml",
))
def show_config_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or a scenario TOML file"),
) -> None:
    """Print a scenario's resolved configuration (every default filled in) as TOML."""
    from ..config import dump_scenario

    with user_input():
        print(dump_scenario(load_named_scenario(scenario)), end="")


@app.command("simulate", epilog=examples(
    "pancam-graph simulate denver_trail --out obs/ --seed 3",
    "pancam-graph run obs/",
))
def simulate_command(
    scenario: str = typer.Argument("denver_trail", help="bundled scenario name or path to a TOML file"),
    out: Path = typer.Option(..., "--out", help="observation folder to write"),
    seed: int | None = typer.Option(None, "--seed", min=0, help="override the scenario's seed"),
    no_truth: bool = typer.Option(False, "--no-truth", help="leave the reference poses (truth.kitti) out"),
    errors: str | None = typer.Option(None, "--errors", help=SourceOptions.help("errors")),
) -> None:
    """Write a scenario's simulated observations as an observation folder (docs/observation_format.md),
    the input an external front-end would give `pancam-graph run`."""
    from ..api import simulate

    with console.status(f"simulating {escape(scenario)}"):
        traverse = simulate(scenario, out, seed=seed, truth=not no_truth, errors=errors)
    console.print(f"{len(traverse.stops)} stops written to {out}")


@app.command("scenarios", epilog=examples(
    "pancam-graph scenarios",
))
def scenarios_command() -> None:
    """List the bundled scenarios."""
    import tomllib
    from importlib import resources

    # their descriptions read straight from the files: validating them needs the whole
    # configuration model, seconds on a loaded machine for a list (show-config validates)
    for path in sorted(resources.files("pancam_graph.scenarios").iterdir(), key=lambda p: p.name):
        if path.name.endswith(".toml"):
            try:
                description = tomllib.loads(path.read_text(encoding="utf-8")).get("description", "")
            except tomllib.TOMLDecodeError as exc:  # listed anyway, with its problem
                description = f"(invalid: {exc})"
            print(f"{path.name.removesuffix('.toml'):16s} {description}")
