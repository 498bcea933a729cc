"""Benchmarks: full runs timed over seeds (with Monte Carlo consistency), the image front-end
per stage, and the site panoramas' matching against the renderer's truth. Each returns one JSON
document with the machine's load average before and after (the machine may be shared)."""

from __future__ import annotations

import dataclasses
import os
import resource
import time
from pathlib import Path

from ..config import load_scenario, resolve_scenario
from ..errors import ConfigError, ResultsError
from ..runtime.processes import cores, hold_malloc_thresholds, start_process_server
from ..runtime.scratch import temporary_folder
from ..solve.group import ProgressCallback


def _load(scenario: str):
    return load_scenario(resolve_scenario(scenario))


def _report(progress: ProgressCallback | None, stage: str, done: int, total: int) -> None:
    if progress is not None:
        progress(stage, done, total)


def bench_runs(scenario: str, seed: int | None = None, seeds: int = 1, rerun: bool = False, monte_carlo: int = 0,
               plot: Path | None = None, progress: ProgressCallback | None = None) -> dict:
    """Time full runs (all configurations) of `seeds` consecutive seeds from `seed` (default
    the scenario's): iSAM2 update percentiles, VO and wall time, memory, cost along the path;
    with `rerun`, each seed also recorded; with `monte_carlo`, efficiency and ANEES over the
    seeds. The load average before and after goes with the figures."""
    import numpy as np

    from ..solve.pipeline import run_scenario
    from ..solve.results import RunOptions, cost_along, memory_along, percentiles

    seeds = max(seeds, monte_carlo)
    load_before = os.getloadavg()
    hold_malloc_thresholds()  # as a run does
    sc = _load(scenario)
    first = sc.seed if seed is None else seed
    results, walls, recorded_walls = [], [], []
    options = RunOptions(processes=cores())
    if options.processes > 1:
        start_process_server()
    for s in range(first, first + seeds):
        start = time.perf_counter()
        results.append(run_scenario(sc, dataclasses.replace(options, seed=s)))
        walls.append(time.perf_counter() - start)
        if rerun:
            recorded_walls.append(_time_recorded_run(sc, s))
        if progress is not None:
            extra = f", with --rerun save {recorded_walls[-1]:.1f} s" if rerun else ""
            progress(f"seed {s}: {walls[-1]:.1f} s{extra}", s - first + 1, seeds)
    ms = np.concatenate([r.update_ms for r in results])
    report = {
        "scenario": sc.name,
        "seeds": [r.seed for r in results],
        "stops": [len(r.traverse.stops) for r in results],
        "isam2_update_ms": {**percentiles(ms), "count": int(len(ms))},
        "isam2_update_ms_per_config": {
            n: percentiles(np.concatenate([r.configurations[n].update_ms for r in results]))
            for n in results[0].configurations
        },
        "vo_s": float(np.mean([r.vo_s for r in results])),
        "wall_s": float(np.mean(walls)),
        "peak_memory_mb": _peak_memory(results[0]),
        # the first seed's groups of configurations and how long each took in its process
        "groups": [{"label": p.label, "configurations": list(p.configurations), "seconds": round(p.seconds, 2),
                    "cpu_seconds": round(p.cpu_seconds, 2)} for p in results[0].processes],
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
    }
    # the first seed's cost along the path: flat, or growing with the traverse?
    report["isam2_update_ms_per_km"] = cost_along(results[0], 1000.0)
    distance = results[0].reference_distance()
    report["rss_mb_along_path"] = {group: [{"at_m": round(float(distance[k]), 1), "rss_mb": round(mb, 1)}
                                           for k, mb in samples]
                                   for group, samples in memory_along(results[0]).items()}
    if plot is not None:
        from ..viz.plots import plot_cost_along

        try:
            plot_cost_along(report["isam2_update_ms_per_km"], report["rss_mb_along_path"],
                            f"{sc.name} seed {first}", plot)
        except OSError as exc:
            raise ResultsError(f"--plot {plot}: cannot write it: {exc.strerror}") from None
        report["plot"] = str(plot)
    if rerun:
        ratios = np.array(recorded_walls) / np.array(walls)
        report["rerun_save"] = {
            "wall_s": float(np.mean(recorded_walls)),
            "overhead_pct": 100.0 * (float(np.sum(recorded_walls)) / float(np.sum(walls)) - 1.0),
            "overhead_pct_median_pair": 100.0 * (float(np.median(ratios)) - 1.0),
            "note": "total wall with a RerunRecorder saving to a temporary .rrd vs without; each seed run "
                    "both ways back to back",
        }
    if seeds > 1:
        report["over_seeds"] = {
            n: {
                stat: {"mean": float(np.mean(v)), "std": float(np.std(v)), "max": float(np.max(v))}
                for stat, v in (
                    ("relative_closure_pct", [r.configurations[n].metrics.relative_closure_pct for r in results]),
                    ("ate_rmse_m", [r.configurations[n].metrics.ate_rmse_m for r in results]),
                    ("bridged_stops", [r.configurations[n].bridged_stops for r in results]),
                )
            }
            for n in results[0].configurations
        }
    if monte_carlo:
        from ..evaluation.consistency import monte_carlo_summary

        report["monte_carlo"] = {n: monte_carlo_summary([r.configurations[n].consistency for r in results],
                                                        [r.configurations[n].nees.last for r in results])
                                 for n in results[0].configurations
                                 if all(r.configurations[n].consistency is not None for r in results)}
    return report


def _peak_memory(result) -> dict[str, dict[str, float]]:
    """Peak memory (MB): the most the run's processes held at once (sampled), and each
    process's own peak and their sum: this one's (its peak so far), and those that ran groups
    of configurations side by side (the most they held at their checkpoints). Resident set
    size counts the pages the workers share (the fork server's imports) in each; the
    proportional set size (sampled at checkpoints) counts each its share."""
    from ..runtime.memory import pss_mb

    rss = {"this process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    pss = {"this process": pss_mb() or 0.0}
    for process in result.processes:
        if process.memory_mb and process.pid != os.getpid():
            label = f"process {process.pid}"
            rss[label] = max(rss.get(label, 0.0), max(mb for _, mb in process.memory_mb))
            pss[label] = max(pss.get(label, 0.0), process.peak_pss_mb or 0.0)
    return {"at_once": round(result.peak_memory_mb, 1) if result.peak_memory_mb is not None else None,
            "rss": {**{k: round(v, 1) for k, v in rss.items()}, "sum": round(sum(rss.values()), 1)},
            "pss": {**{k: round(v, 1) for k, v in pss.items()}, "sum": round(sum(pss.values()), 1)}}


def bench_monte_carlo_sweep(scenario: str, seed: int | None, seeds: int, workers: int) -> dict:
    """bench --monte-carlo as a sweep: the same summary, the runs on a local Dask cluster."""
    import numpy as np

    from ..config import resolve_scenario
    from ..sweep.runner import run_sweep
    from ..sweep.spec import SweepSpec, plan
    from ..sweep.table import monte_carlo, run_rows

    sc = _load(scenario)
    first = sc.seed if seed is None else seed
    spec = SweepSpec(scenarios=[str(resolve_scenario(scenario).resolve())], seeds=seeds, first_seed=first)
    start = time.perf_counter()
    with temporary_folder("bench") as folder:
        records = run_sweep(plan(spec, Path(folder)), spec.timeout_s, workers)
        failed = [r for r in records if r.status != "done"]
        if failed:
            raise ResultsError(f"{len(failed)} of {len(records)} runs failed; first: {failed[0].run.name}: "
                               f"{failed[0].message}")
        rows = run_rows(records)
    configs = dict.fromkeys(row["config"] for row in rows)
    report = {"scenario": sc.name, "seeds": list(range(first, first + seeds)), "workers": workers,
              "wall_s": time.perf_counter() - start,
              "monte_carlo": {c: mc for c in configs if (mc := monte_carlo([r for r in rows if r["config"] == c]))}}
    report["over_seeds"] = {
        c: {stat: {"mean": float(np.mean(v)), "max": float(np.max(v))}
            for stat in ("relative_closure_pct", "ate_rmse_m")
            if (v := [r[stat] for r in rows if r["config"] == c and r.get(stat) is not None])}
        for c in configs}
    return report


def bench_sites(source: str | None, compared_sites: int = 3, progress: ProgressCallback | None = None) -> dict:
    """The site panoramas of an image folder: pan/tilt-aided against unaided (SIFT) matching of
    overlapping frames on the first `compared_sites` sites (SIFT is slow: a few sites), and
    the tie points between every pair of sites; each checked against the renderer's truth when
    the folder names a bundled scenario."""
    import numpy as np

    from ..config import FrontendConfig, bundled_scenarios
    from ..frontend.motion import VoMotions
    from ..frontend.panorama import PanoramaMatcher, PanoramaView, unaided_matches
    from ..render.truth import RenderedTruth
    from ..sources import image_folder
    from ..sources.site_images import images_by_stop, with_site_panoramas
    from ..store.observation_folder import is_image_folder, read_observations

    if source is None or not is_image_folder(Path(source)):
        raise ConfigError(f"bench sites {source or ''}: give an image folder with site panoramas "
                          "(pancam-graph render SCENARIO --out FOLDER writes one)")
    load_before = os.getloadavg()
    obs = read_observations(Path(source))
    scenario = bundled_scenarios().get(obs.traverse.name)
    truth = None if scenario is None or obs.truth is None else RenderedTruth(
        _load(str(scenario)), obs.seed, obs.truth.world_T_body, obs.traverse.rig.wac)
    pairs = image_folder.FramePairs(obs)
    tracked = image_folder.load(Path(source), FrontendConfig(), sites=False,
                                progress=lambda _, done, total: _report(progress, "front-end", done, total))
    vo = VoMotions.estimate(tracked.traverse, tracked.estimator)
    _, report = with_site_panoramas(obs, list(tracked.traverse.stops), pairs.read_view, vo, FrontendConfig(),
                                    progress=lambda _, done, total: _report(progress, "site panoramas", done, total),
                                    read_hrc=pairs.read_hrc if obs.traverse.rig.hrc is not None else None)
    # aided against unaided matching of overlapping frames, on the first sites
    rig = obs.traverse.rig
    matcher = PanoramaMatcher(rig.wac, rig.baseline_m)
    aided = {"frame_pairs": 0, "links": 0, "seconds": 0.0, "errors": []}
    unaided = {"frame_pairs": 0, "matches": 0, "seconds": 0.0, "errors": []}
    by_stop = images_by_stop(obs)
    for stop in list(by_stop)[:compared_sites]:
        views = [PanoramaView(im.pan_rad, im.tilt_rad, rig.body_T_left(im.pan_rad, im.tilt_rad).matrix(),
                              *pairs.read_view(im)) for im in by_stop[stop]]
        matcher(stop, 0, views)
        for i, a in enumerate(views):
            for b in views[i + 1:]:
                start = time.perf_counter()
                links = matcher.overlap_matches(a, b)
                aided["seconds"] += time.perf_counter() - start
                if not links:
                    continue
                aided["frame_pairs"] += 1
                aided["links"] += len(links)
                start = time.perf_counter()
                ua, ub = unaided_matches(a, b)
                unaided["seconds"] += time.perf_counter() - start
                unaided["frame_pairs"] += 1
                unaided["matches"] += len(ua)
                if truth is None:
                    continue
                uv_a = dict(zip(a.observations.track_ids.tolist(), a.observations.uvv[:, [0, 2]], strict=True))
                uv_b = dict(zip(b.observations.track_ids.tolist(), b.observations.uvv[:, [0, 2]], strict=True))
                aided["errors"] += [truth.transfer_error((stop, a.body_T_camera, uv_a[ta]),
                                                         (stop, b.body_T_camera, uv_b[tb])) for ta, tb in links]
                unaided["errors"] += [truth.transfer_error((stop, a.body_T_camera, pa), (stop, b.body_T_camera, pb))
                                      for pa, pb in zip(ua, ub, strict=True)]

    def scored(errors: list[float], within_px: float) -> dict:
        e = np.asarray(errors)
        if not len(e):
            return {}
        return {f"correct_within_{within_px:g}px_pct": round(100.0 * float(np.mean(e < within_px)), 2),
                "median_error_px": round(float(np.median(e)), 3)}

    site = {s.stop: s for s in report.sites}
    pair_rows, tie_errors = [], []
    for pair in report.pairs:
        errors = [] if truth is None else [truth.transfer_error(
            (pair.a_stop, site[pair.a_stop].views[t.a_view].body_T_camera, t.a_uvv[[0, 2]]),
            (pair.b_stop, site[pair.b_stop].views[t.b_view].body_T_camera, t.b_uvv[[0, 2]]))
            for t in pair.result.ties]
        tie_errors += errors
        pair_rows.append({"a_stop": pair.a_stop, "b_stop": pair.b_stop, "distance_m": round(pair.distance_m, 1),
                          "adjacent": pair.b_stop == report.next_site(pair.a_stop),
                          "candidates": pair.result.candidates, "matched": len(pair.result.matches),
                          "verified": len(pair.result.ties), "seconds": round(pair.result.seconds, 2),
                          "note": pair.result.note, **scored(errors, 3.0)})
    adjacent = [r["verified"] for r in pair_rows if r["adjacent"]]
    hrc_rows, hrc_errors = [], []
    for stop, frames in report.hrc.items():
        for m in frames:
            body_T_hrc = rig.body_T_hrc(m.pan_rad, m.tilt_rad).matrix()
            errors = [] if truth is None else [
                truth.transfer_error((stop, site[stop].views[v].body_T_camera, wac_uv), (stop, body_T_hrc, uv), rig.hrc)
                for v, wac_uv, uv in zip(m.wac_view, m.wac_uv, m.uv, strict=True)]
            hrc_errors += errors
            hrc_rows.append({"stop": stop, "pan_deg": round(float(np.rad2deg(m.pan_rad)), 1),
                             "predicted": m.predicted, "matched": len(m.track_ids),
                             "dropped_for_shift": m.disagreeing,
                             "shift_hrc_px": [round(float(x), 1) for x in m.shift_px],
                             "correct_within_7px": int(np.sum(np.array(errors) < 7.0)) if truth is not None else None,
                             "seconds": round(m.seconds, 3)})
    return {
        "source": source, "sites": len(report.sites), "summary": report.summary(),
        "truth": "renderer depth at the true poses" if truth is not None else None,
        "ties": {"total": sum(len(p.result.ties) for p in report.pairs),
                 "adjacent_pairs_fewest": min(adjacent) if adjacent else 0,
                 "adjacent_pairs_median": float(np.median(adjacent)) if adjacent else 0.0,
                 **scored(tie_errors, 3.0), **scored(tie_errors, 2.0), "pairs": pair_rows},
        "hrc": {
            "frames": len(hrc_rows),
            "matched_median": float(np.median([r["matched"] for r in hrc_rows])) if hrc_rows else 0.0,
            "matched_fewest": min((r["matched"] for r in hrc_rows), default=0),
            "correct_fewest": min((r["correct_within_7px"] or 0 for r in hrc_rows), default=0),
            **scored(hrc_errors, 7.0), **scored(hrc_errors, 3.0),
            "note": "HRC pixels against where the WAC feature's terrain point is in the HRC image; 7 HRC px is "
                    "one WAC pixel",
            "frames_detail": hrc_rows,
        },
        "overlapping_frames": {
            "sites": min(compared_sites, len(by_stop)),
            "pan_tilt_aided": {k: v for k, v in aided.items() if k != "errors"} | scored(aided["errors"], 2.0),
            "unaided_sift": {k: v for k, v in unaided.items() if k != "errors"} | scored(unaided["errors"], 2.0),
            "note": "aided: seconds of back-projection, warping and optical flow over every frame pair (the "
                    "stereo features are the site's own); unaided: SIFT detection and matching of the left "
                    "images and a RANSAC fundamental matrix, on the frame pairs the aided matching found "
                    "overlapping",
        },
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
    }


def bench_frontend(source: str | None, detector: str | None = None, progress: ProgressCallback | None = None) -> dict:
    """The image front-end's time per frame and per stage on stereo images, as `run` drives it."""
    import numpy as np

    from ..config import FrontendConfig
    from ..frontend.tracker import StereoTracker
    from ..sources import source_for, stereo_image_sources
    from ..sources.frames import frame_ms, track_frames

    if source is None or not source_for(source).stereo_images:
        raise ConfigError(f"bench frontend {source or ''}: give stereo images ({stereo_image_sources()}, e.g. "
                          "../shared/data/real/kitti_odometry_51)")
    config = FrontendConfig(detector=detector or "gftt")
    frames = source_for(source).frames(Path(source))
    stops, read_raw, size, rectify, camera_motion = (frames.stops, frames.read_raw, frames.size, frames.rectify,
                                                     frames.camera_motion)
    tracker = StereoTracker(config)
    read_ms: list[float] = []

    def read_pair(k: int):
        start = time.perf_counter()
        pair = read_raw(k)
        read_ms.append((time.perf_counter() - start) * 1e3)
        return pair if rectify is None else rectify(pair, tracker.times)

    load_before = os.getloadavg()
    # the run's own loop over the frames, so the bench times what `run` does
    tracked = track_frames(stops, read_pair, tracker, lambda tracked, notes: tracked,
                           progress=lambda _, done, total: _report(progress, "front-end", done, total),
                           camera_motion=camera_motion if config.odometry_aided else None)
    frame = frame_ms(tracker)
    features = [len(s.stereo) for s in tracked]
    stages = tracker.times.summary()
    stages.pop("frame")
    return {
        "source": source, "detector": config.detector, "frames": len(tracked), "image_size": [size[1], size[0]],
        "frame_ms": {"median": float(np.median(frame)), "p95": float(np.percentile(frame, 95)),
                     "mean": float(frame.mean())},
        "stages_ms": stages, "image_read_ms_median": float(np.median(read_ms)),
        "features_per_frame_median": float(np.median(features)),
        "load_average_1min": {"before": load_before[0], "after": os.getloadavg()[0]},
        "note": "frame_ms: images in memory -> rectified (raw images) -> observations (reading the images "
                "not included); gftt: corner detection runs beside temporal tracking, whose time includes "
                "the overlap, and detect is what is left of it",
    }


def _time_recorded_run(scenario, seed: int) -> float:
    from ..solve.pipeline import run_scenario
    from ..solve.results import RunOptions
    from ..viz.rerun_live import RerunRecorder
    from ..viz.rerun_sink import RerunTarget, open_recording

    with temporary_folder("bench") as tmp:
        start = time.perf_counter()
        recording = open_recording(RerunTarget("save", path=Path(tmp) / "bench.rrd"), "bench")
        run_scenario(scenario, RunOptions(seed=seed), listener=RerunRecorder(recording))
        recording.close()
        return time.perf_counter() - start
