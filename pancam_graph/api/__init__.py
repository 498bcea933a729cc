"""The library: what each command does, as calls that return typed results and never print.

    import pancam_graph
    outcome = pancam_graph.run("short_trail", seed=0, out="results/short")
    outcome.result.configurations["vo_sites"].metrics.ate_rmse_m

The command line (cli/) parses arguments into these calls and prints what they return.
Errors are raised as the package's typed errors (errors.py).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import ConfigError, FrameError, GeodesyError, RunInterrupted, ViewerUnavailable
from ..evaluation.evaluate import Evaluation
from ..records import Traverse
from ..runtime.atomic import writing
from ..runtime.processes import cores, hold_malloc_thresholds, start_process_server, unguarded_script_call
from ..solve.group import ProgressCallback
from ..solve.results import RunOptions, RunResult
from ..solve.state import RunState
from ..sources import SourceOptions, open_source, source_for, stereo_image_sources
from ..sources.registry import SourceData
from ..viz.rerun_sink import OpenRecording as Recording
from ..viz.rerun_sink import RerunTarget

if TYPE_CHECKING:
    from ..frontend.calibrate import StereoFit
    from ..geometry.stereo_pair import StereoCalibration
    from ..store.results_folder import SavedRun


@dataclass(frozen=True)
class RunOutcome:
    """A finished run: its result, where it was written, and what else happened on the way."""

    result: RunResult
    folder: Path  # the results folder (metrics.json, steps.csv, trajectories, report.md)
    report: Path
    rejected: tuple[str, ...] = ()  # what the source's reader left out, with reasons
    warnings: tuple[str, ...] = ()  # e.g. a viewer that did not answer (the run went on without it)
    checkpoints: int = 0  # saved for --resume
    checkpoint_s: float = 0.0
    recording: Recording | None = None  # closed; `served_url` of a served one

    @property
    def metrics_path(self) -> Path:
        return self.folder / "metrics.json"


@dataclass(frozen=True)
class ResumePoint:
    """A killed run's staging folder and what it had reached."""

    partial: Path
    out: Path
    data: SourceData
    options: RunOptions
    states: list[RunState] = field(default_factory=list)


def default_out(data: SourceData) -> Path:
    label = f"seed{data.seed}-" if data.scenario is not None else ""
    return Path("results") / f"{data.traverse.name}-{label}{datetime.now():%Y%m%d-%H%M%S}"


def check_out(out: Path | None, option: str = "--out") -> None:
    """Results are never written over: `out` must be new or an empty folder, and no live run may
    be writing it."""
    from ..store.results_folder import refuse_if_in_use

    if out is None:
        return
    refuse_if_in_use(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise ConfigError(f"{option} {out}: is a file, not a folder")
    if any(out.iterdir()):
        raise ConfigError(f"{option} {out}: folder exists and is not empty; choose another {option}")


def open_data(source: str | Path, options: SourceOptions = SourceOptions(), out: Path | None = None,
              progress: ProgressCallback | None = None, vo_error_model: str | None = None,
              processes: int | None = None) -> SourceData:
    """Read a source (an image source runs the front-end over every frame). A bad frame that
    stops the front-end leaves what it tracked before as an observation folder in
    <out>.partial/observations, and the FrameError says so. `vo_error_model`: the VO error model
    to use instead of the source's own (config.VO_ERROR_MODELS). `processes`: the run's (default
    every core); with more than one, a simulation runs in a process of its own
    (processes.call_apart)."""
    hold_malloc_thresholds()  # before the source's allocations
    try:
        data = open_source(str(source), options, progress, apart=(processes or cores()) > 1)
    except FrameError as exc:
        raise _kept_frontend_work(exc, out) from None
    return _with_vo_error_model(data, vo_error_model)


def check_configs(source: str | Path, configs: tuple[str, ...] | None) -> None:
    """Refuse a requested configuration that its name alone rules out (unknown, a kind it lacks),
    before the source loads: a typo costs no simulation or front-end run. What the traverse
    must feed is checked once it is loaded."""
    if configs is None:
        return
    from ..solve.pipeline import configuration_kinds
    from ..sources import estimator_before_loading

    estimator = estimator_before_loading(str(source))
    if estimator is not None:  # None: only loading the source tells its configurations
        configuration_kinds(estimator, configs)


def _with_vo_error_model(data: SourceData, name: str | None) -> SourceData:
    """The source with the VO error model `name` in effect (as it is: None, or its own)."""
    if name is None or name == data.estimator.vo_error_model:
        return data
    from ..config import with_vo_error_model

    estimator = with_vo_error_model(data.estimator, name)
    scenario = None if data.scenario is None else data.scenario.model_copy(update={"estimator": estimator})
    return dataclasses.replace(data, estimator=estimator, scenario=scenario)


def _kept_frontend_work(exc: FrameError, out: Path | None) -> FrameError:
    from ..store.observation_writer import write_observations
    from ..store.results_folder import results_folder

    data = exc.partial
    if data is None:
        return exc
    out = out or Path("results") / f"{data.traverse.name}-{datetime.now():%Y%m%d-%H%M%S}"
    kept = out.with_name(out.name + ".partial") / "observations"
    try:
        with results_folder(out) as folder:
            with writing(folder / "observations", "the front-end's observations"):
                write_observations(folder / "observations", data.traverse, data.estimator, data.seed, data.truth)
            raise exc  # leaving as a failed run keeps the folder as <out>.partial
    except FrameError:
        pass
    n = len(data.traverse.stops)
    return FrameError(f"{exc}\nthe front-end's observations of stops 0-{n - 1} are kept in {kept} (`pancam-graph "
                      f"run {kept}` runs the back-end on them); --skip-bad-frames leaves a bad stop to the VO bridge "
                      "instead", exc.stop)


def run(source: str | Path = "denver_trail", *, out: Path | str | None = None, seed: int | None = None,
        configs: tuple[str, ...] | None = None, batch: bool = False, processes: int | None = None,
        source_options: SourceOptions | None = None, rerun: RerunTarget | None = None,
        checkpoint_every_s: float = 30.0, figures: bool = True, progress: ProgressCallback | None = None,
        opened: SourceData | None = None, on_viewer: Callable[[str], None] | None = None,
        vo_error_model: str | None = None) -> RunOutcome:
    """Run a source (a bundled scenario name, a scenario TOML, an observation or image folder, a
    ROS bag, a KITTI raw drive or odometry sequence) through every configuration it can feed (or
    `configs`), and write the results folder `out` (default results/<name>-<time>): the one
    metrics.json schema, steps.csv, trajectories, plots (`figures`) and report.md. `processes`:
    default every core. `opened`: the source already read (open_data). `on_viewer`: told the web
    viewer's address as soon as a served recording (`rerun` mode serve) is up, before the run.
    `vo_error_model`: the VO error model instead of the source's own (config.VO_ERROR_MODELS)."""
    from ..solve.pipeline import select_configurations

    hold_malloc_thresholds()
    out = Path(out) if out is not None else None
    options = RunOptions(seed=seed, configs=configs, batch=batch, processes=processes or cores(),
                         vo_error_model=vo_error_model)
    if options.processes > 1:
        check_script_guard()
        start_process_server()  # it imports while the source loads
    check_out(out)
    source_options = source_options or SourceOptions(seed=seed)
    if opened is None:
        check_configs(source, options.configs)
    data = _with_vo_error_model(opened, vo_error_model) if opened else open_data(source, source_options, out,
                                                                                   progress, vo_error_model,
                                                                                   options.processes)
    select_configurations(data.estimator, data.traverse, options.configs)  # before anything is written
    return _into_folder(data, options, out, rerun, checkpoint_every_s, figures, progress, on_viewer=on_viewer)


def check_script_guard() -> None:
    """Refuse, before anything is written, a run on several cores called from a script's top
    level outside `if __name__ == "__main__":`: its worker processes import the script again."""
    where = unguarded_script_call()
    if where is not None:
        raise ConfigError(f"{where}: pancam_graph is called at the script's top level; a run on several cores "
                          "starts worker processes that import the script again: put the call under "
                          "`if __name__ == \"__main__\":` (or pass processes=1)")


def resume_point(resume: Path | str) -> ResumePoint:
    """A killed run's staging folder (its <out>.partial, or the <out> it was to become) and its
    last checkpoint."""
    from ..store.checkpoint import read_checkpoint

    resume = Path(resume)
    if resume.name.endswith(".partial"):
        partial, out = resume, resume.with_name(resume.name.removesuffix(".partial"))
    elif resume.with_name(resume.name + ".partial").is_dir():
        partial, out = resume.with_name(resume.name + ".partial"), resume
    else:
        raise ConfigError(f"--resume {resume}: expected a killed run's <out>.partial folder")
    inputs, states = read_checkpoint(partial)
    return ResumePoint(partial, out, inputs.data, inputs.options, states)


def resume(point: ResumePoint | Path | str, *, processes: int | None = None, rerun: RerunTarget | None = None,
           checkpoint_every_s: float = 30.0, figures: bool = True, progress: ProgressCallback | None = None,
           on_viewer: Callable[[str], None] | None = None) -> RunOutcome:
    """Go on with a killed run from its last checkpoint, with its own source and options, in its
    own staging folder."""
    if not isinstance(point, ResumePoint):
        point = resume_point(point)
    hold_malloc_thresholds()
    options = point.options if processes is None else dataclasses.replace(point.options, processes=processes)
    if options.processes > 1:
        start_process_server()
    return _into_folder(point.data, options, point.out, rerun, checkpoint_every_s, figures, progress,
                            point.states, on_viewer)


def _into_folder(data: SourceData, options: RunOptions, out: Path | None, target: RerunTarget | None,
                     checkpoint_every_s: float, figures: bool, progress: ProgressCallback | None,
                     states: list[RunState] | None = None,
                     on_viewer: Callable[[str], None] | None = None) -> RunOutcome:
    from ..solve import pipeline
    from ..store.checkpoint import CheckpointWriter, RunInputs, remove_checkpoint
    from ..store.results_folder import results_folder, write_run

    out = out or default_out(data)
    recording = checkpoints = None
    warnings = []
    try:
        with results_folder(out, resume=states is not None) as folder:
            checkpoints = CheckpointWriter(folder, RunInputs(data, options), checkpoint_every_s,
                                           resumed=bool(states))
            listener = None
            if target is not None:
                from ..viz.rerun_live import RerunRecorder
                from ..viz.rerun_sink import open_recording

                if target.mode == "save" and target.path is None:
                    target = dataclasses.replace(target, path=folder / "recording.rrd")
                try:
                    recording = open_recording(target, f"{data.traverse.name} seed {data.seed}", on_viewer)
                    listener = RerunRecorder(recording)
                except ViewerUnavailable as exc:  # the results are the product, the viewer is not
                    warnings.append(f"{exc}; running without it")
            try:
                result = pipeline.run(data.traverse, data.truth, data.estimator, data.seed, options, progress,
                                      listener, source=data.info, scenario=data.scenario, held_out=data.held_out,
                                      save=checkpoints, resume=states, vo_motions=data.vo_motions,
                                      # the wall time counts the source's reading (an image source's front-end)
                                      started=None if states else time.perf_counter() - data.load_s)
                # the report's plotting imports matplotlib (tens of MB resident): not while the groups run
                from ..viz.report import write_report

                with writing(folder, "the results"):
                    write_run(result, folder)
                    report = write_report(result, folder, figures)
                remove_checkpoint(folder)
                warnings += _kind_warnings(result)
            finally:
                if recording is not None:  # also on failure: keep what was recorded
                    recording.close()
                    if recording.failure is not None:
                        warnings.append(f"{recording.failure}; the run went on without it")
    except KeyboardInterrupt:
        saved = checkpoints.saved_stops if checkpoints is not None else []
        raise RunInterrupted(out.with_name(out.name + ".partial"), min(saved) if saved else None) from None
    if recording is not None and recording.target.mode == "save" and recording.target.path.parent == folder:
        recording = dataclasses.replace(recording, target=dataclasses.replace(recording.target,
                                                                              path=out / recording.target.path.name))
    return RunOutcome(result, out, out / report.name, data.rejected, tuple(warnings), checkpoints.saves,
                      checkpoints.save_s, recording)


def _kind_warnings(result) -> list[str]:
    """What the kinds left undone that the user must hear of (Kind.warning_counters)."""
    from ..kinds import KINDS

    out = []
    for name, configuration in result.configurations.items():
        for kind in KINDS.values():
            for counter, what in kind.warning_counters.items():
                entries = configuration.counters.get(counter) or []
                if entries:
                    shown = "; ".join(str(e) for e in entries[:5]) + ("; ..." if len(entries) > 5 else "")
                    out.append(f"{name}: {len(entries)} {what}: {shown}")
    return out


def track(source: str | Path, out: Path | str, *, detector: str | None = None, skip_bad_frames: bool = False,
          progress: ProgressCallback | None = None) -> Traverse:
    """Run the image front-end over stereo images and write what it found as an observation
    folder `out`, so the back-end can run again without the images."""
    from ..store.observation_writer import write_observations

    out = Path(out)
    check_out(out)
    if not source_for(str(source)).stereo_images:
        raise ConfigError(f"{source}: track needs stereo images ({stereo_image_sources()})")
    data = open_data(source, SourceOptions(detector=detector, skip_bad_frames=skip_bad_frames or None), out,
                     progress)
    with writing(out, "the observation folder", discard=not out.exists()):
        write_observations(out, data.traverse, data.estimator, data.seed, data.truth)
    return data.traverse


@dataclass(frozen=True)
class CalibrationOutcome:
    """A stereo pair calibrated from control-field images, written to `out`; with the
    calibration it was compared with (`reference`, read from `reference_path`), if any."""

    fit: StereoFit
    out: Path
    reference: StereoCalibration | None
    reference_path: Path | None


def calibrate(folder: Path | str, out: Path | str, *, field: Path | str | None = None,
              truth: Path | str | None = None, progress: ProgressCallback | None = None) -> CalibrationOutcome:
    """Calibrate a stereo pair from images of a 3-D control field (the dissertation's section 4.2)
    and write it as OpenCV YAML with its rectification; compared with `truth` (default: the
    folder's truth_calibration.yaml when there is one)."""
    from ..formats.calibration import read_opencv_yaml, write_opencv_yaml
    from ..formats.calibration_images import TRUTH_FILE, calibrate_folder

    folder, out = Path(folder), Path(out)
    if out.exists() and out.is_dir():
        raise ConfigError(f"--out {out}: is a folder; give the YAML file to write")
    truth = Path(truth) if truth is not None else (folder / TRUTH_FILE if (folder / TRUTH_FILE).is_file() else None)
    reference = read_opencv_yaml(truth) if truth is not None else None
    fit = calibrate_folder(folder, Path(field) if field is not None else None, progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_opencv_yaml(out, fit.calibration, rectification=True)
    return CalibrationOutcome(fit, out, reference, truth)


def simulate(scenario: str | Path, out: Path | str, *, seed: int | None = None, truth: bool = True,
             errors: str | None = None) -> Traverse:
    """Write a scenario's simulated observations as an observation folder; `errors`: an error
    profile in place of the scenario's [errors] table (ideal or realistic)."""
    from ..config import load_scenario, resolve_scenario
    from ..sim import simulate as simulate_scenario
    from ..store.observation_writer import write_observations

    sc = load_scenario(resolve_scenario(str(scenario)), errors)
    out = Path(out)
    check_out(out)
    seed = sc.seed if seed is None else seed
    traverse, true = simulate_scenario(sc, seed)
    with writing(out, "the observation folder", discard=not out.exists()):
        write_observations(out, traverse, sc.estimator, seed, true if truth else None, sc.rig)
    return traverse


def evaluate(estimate: Path | str, reference: Path | str, *, align: str = "none", max_dt_s: float = 0.01,
             rpe_delta_m: float = 10.0, origin: tuple[float, float, float] | None = None, gps_sigma_m: float = 1.0,
             lever_arm: tuple[float, float, float] | None = None, out: Path | str | None = None) -> Evaluation:
    """Compare a trajectory with a reference (or a GPS log) with the run's metrics; with `out`,
    write metrics.json in the run's schema (one configuration, named after the estimate) and a
    plot. Against a GPS log, an estimate with attitudes is compared at the antenna: `lever_arm`
    (body frame, m), by default the one saved beside the estimate (a results folder's)."""
    from ..evaluation.evaluate import at_point_of_body, evaluate_trajectories
    from ..formats.trajectories import read_trajectory
    from ..geometry.geodesy import LocalFrame
    from ..store.results_folder import read_gps_lever_arm, read_local_frame

    estimate, reference = Path(estimate), Path(reference)
    if align not in ("none", "se3", "yaw"):
        raise ConfigError(f"--align {align!r}: expected none, se3 or yaw")
    if not rpe_delta_m > 0.0:
        raise ConfigError(f"--rpe-delta {rpe_delta_m:g}: the relative pose error's distance must be more than 0 m")
    if origin is None:
        frame = read_local_frame(estimate.parent)
    else:
        try:
            frame = LocalFrame(*origin)
        except GeodesyError as exc:
            raise ConfigError(f"--origin {','.join(f'{v:g}' for v in origin)}: {exc}") from None
    est = read_trajectory(estimate, frame, gps_sigma_m)
    ref = read_trajectory(reference, frame, gps_sigma_m)
    if (est.geodetic is None) != (ref.geodetic is None) and frame is None:
        raise ConfigError(f"{reference if ref.geodetic is not None else estimate}: a GPS log needs the ENU "
                          "origin of the other trajectory: give --origin LAT,LON,H")
    import numpy as np

    arm = None
    if ref.geodetic is not None and est.geodetic is None and est.world_T_body is not None:
        arm = np.asarray(lever_arm, dtype=float) if lever_arm is not None else read_gps_lever_arm(estimate.parent)
        if arm is not None:
            est = at_point_of_body(est, arm)
    result = evaluate_trajectories(est, ref, align, max_dt_s, rpe_delta_m)
    if arm is not None:
        result = dataclasses.replace(result, lever_arm_m=tuple(float(v) for v in arm))
    if out is not None:
        from ..store.results_folder import write_evaluation
        from ..viz.plots import evaluation_plot

        out = Path(out)
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {out}: is a file, not a folder")
        with writing(out, "the evaluation", discard=not out.exists()):
            out.mkdir(parents=True, exist_ok=True)
            write_evaluation(result, estimate.stem, out)
            evaluation_plot(result, out / "eval.png")
    return result


def view(results: Path | str, target: RerunTarget, saved: SavedRun | None = None,
         on_viewer: Callable[[str], None] | None = None) -> Recording:
    """Replay a finished results folder (`saved`: read already) into rerun with the live run's
    layout; returns the closed recording (a served one stays served until its `stop_serving`;
    `on_viewer` is told its web viewer's address as soon as it is up; its `failure` says why
    it stopped, if it did)."""
    from ..store.results_folder import read_run
    from ..viz.rerun_replay import replay
    from ..viz.rerun_sink import open_recording

    results = Path(results)
    if target.mode == "save" and target.path is None:
        target = dataclasses.replace(target, path=results / "replay.rrd")
    saved = saved or read_run(results)
    recording = open_recording(target, f"{saved.name} (replay of {results.name})", on_viewer)
    replay(saved, recording.stream)
    recording.close()
    return recording


@dataclass(frozen=True)
class AnalysisOutcome:
    """The dissertation's Chapter 3 analysis of some rigs: one row per rig and the files written."""

    rows: list  # analysis.trades rows (optimal FOV, longest site spacing for 1 %, the curves)
    assumptions: object  # analysis.design.Assumptions
    files: list[Path]


def analyze(out: Path | str, rigs: list[str] | None = None, sigma_px: float = 0.5,
            custom: tuple[float, float, float] | None = None,
            progress: Callable[[int, int], None] | None = None) -> AnalysisOutcome:
    """Chapter 3's error analysis for rig presets (default every one) or a `custom` rig (baseline
    m, focal length px, horizontal FOV deg), written into `out` with every assumption."""
    from ..analysis.design import AnalysisRig, Assumptions
    from ..analysis.trades import analyze as analyze_rigs
    from ..geometry.rig import RIG_PRESETS
    from ..viz.analysis_plots import write_analysis

    out = Path(out)
    check_out(out)
    try:
        chosen = ([AnalysisRig("custom", *custom)] if custom is not None
                  else [AnalysisRig.preset(name) for name in (rigs or list(RIG_PRESETS))])
    except ValueError as exc:
        raise ConfigError(f"--rig: {exc}") from None
    assumptions = Assumptions(sigma_px=sigma_px)
    rows = analyze_rigs(chosen, assumptions, progress=progress)
    return AnalysisOutcome(rows, assumptions, write_analysis(rows, assumptions, out))


@dataclass(frozen=True)
class SweepOutcome:
    """A sweep done: every run's record, the table of runs and the summary over seeds, written
    into the sweep folder (runs.csv, summary.csv, runs_status.csv)."""

    records: list
    rows: list[dict]
    summary: list
    folder: Path

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.records)


@dataclass(frozen=True)
class SweepPlan:
    """A sweep specification read and planned into the sweep folder: the runs to do."""

    timeout_s: float
    runs: list
    folder: Path


def plan_sweep(spec: Path | str, out: Path | str, scheduler: str | None = None) -> SweepPlan:
    """Read a sweep specification (scenarios x rigs x estimator variants x seeds) and lay out its
    runs in the sweep folder `out` (runs already done there are skipped when it runs). A
    `scheduler` address is checked first: nothing is written for one that is not there."""
    from ..sweep.runner import check_scheduler
    from ..sweep.spec import load_spec, plan

    spec, out = Path(spec), Path(out)
    specification = load_spec(spec)
    if scheduler is not None:
        check_scheduler(scheduler)
    runs = plan(specification, out, spec.parent)
    (out / "sweep.toml").write_text(spec.read_text(encoding="utf-8"), encoding="utf-8")
    return SweepPlan(specification.timeout_s, runs, out)


def sweep(planned: SweepPlan, *, workers: int = 2, scheduler: str | None = None,
          progress: Callable | None = None) -> SweepOutcome:
    """A planned sweep's runs on Dask, one task per run (`progress(record, done, total)` hears each
    that ends); a run that fails or times out is recorded and the others go on. Then the table of
    runs and the summary over seeds."""
    from ..sweep.runner import run_sweep
    from ..sweep.table import run_rows, summarize, write_tables

    records = run_sweep(planned.runs, planned.timeout_s, workers, scheduler, progress)
    rows = run_rows(records)
    summary = summarize(rows)
    write_tables(planned.folder, records, rows, summary)
    return SweepOutcome(records, rows, summary, planned.folder)


__all__ = ["AnalysisOutcome", "ProgressCallback", "ResumePoint", "RunInterrupted", "RunOptions", "RunOutcome",
           "SourceOptions", "SweepOutcome", "SweepPlan", "analyze", "check_configs", "check_out", "evaluate",
           "open_data", "plan_sweep", "resume", "resume_point", "run", "simulate", "sweep", "track", "view"]
