"""The documents a results folder holds, laid out once: metrics.json (a run's, or a trajectory
compared with a reference by `eval`), run.toml (the whole resolved configuration) and the
command line that reproduces the run."""

from __future__ import annotations

import numpy as np

from ..config import SourceOptions
from ..kinds import COUNTER_DEFAULTS
from ..solve.results import RunResult, percentiles

# metrics.json's layout: every command that writes one (run, eval) writes this version; a reader
# (sweep tables, view) takes the versions it knows. 2: `schema` and `source.kind` in every file.
METRICS_SCHEMA = 2


def evaluation_document(evaluation, name: str) -> dict:
    """metrics.json of a trajectory compared with a reference (`eval`): the run's layout, one
    configuration named after the estimate."""
    return {"schema": METRICS_SCHEMA, "scenario": name,
            "source": {"kind": "trajectory", "path": evaluation.estimate.source, "notes": [], "options": {}},
            "reference": evaluation.reference.source, "evaluation": evaluation.as_dict(),
            "configs": {name: evaluation.metrics.as_dict()}}


def metrics_document(result: RunResult) -> dict:
    """The content of metrics.json."""
    vo_motions = [m for m in result.motions[1:] if m is not None]
    configs = {}
    for name, c in result.configurations.items():
        entry: dict = {"kinds": list(c.kinds)}
        entry.update(c.metrics.as_dict() if c.metrics is not None else {})
        if c.consistency is not None:
            entry.update(c.consistency.as_dict())
        if c.nees is not None:
            entry.update(c.nees.as_dict())
            entry.setdefault("anees", c.nees.anees)  # without a bound (CRLB), or against GPS fixes
        entry.update(bridged_stops=c.bridged_stops, landmarks=c.landmarks)
        entry.update({name: c.counter(name) for name in COUNTER_DEFAULTS if name not in entry})
        entry.update(
            interpolated_poses=len(c.interpolated),
            solver=c.solver,
            isam2_update_ms=percentiles(c.update_ms),
            vs_gps=c.metrics_vs_gps.as_dict() if c.metrics_vs_gps is not None else None,
            vs_held_out_gps=c.holdout.as_dict() if c.holdout is not None else None,
        )
        for key, value in c.counters.items():
            entry.setdefault(key, value)
        configs[name] = entry
    return {
        "schema": METRICS_SCHEMA,
        "scenario": result.name,
        "source": {"kind": result.source.kind, "path": result.source.path, "notes": list(result.source.notes),
                   "options": result.source.options},
        "seed": result.seed,
        "rig": result.traverse.rig.name,
        "stops": len(result.traverse.stops),
        "sites": sum(s.is_site for s in result.traverse.stops),
        "gps_fixes": len(result.traverse.gps_fixes),
        "gps_fixes_held_out": len(result.held_out_fixes),
        "reference": result.source.reference + " (configs.*), GPS fixes in the graph (configs.*.vs_gps)"
                     + (", held-out GPS fixes (configs.*.vs_held_out_gps)" if result.held_out_fixes else ""),
        "vo": {
            "stops_bridged": sum(m.bridged for m in vo_motions),
            "bridge_sources": sorted({m.source for m in vo_motions if m.bridged}),
            "median_inliers": float(np.median([m.vo_inliers for m in vo_motions])) if vo_motions else 0.0,
        },
        "configs": configs,
        "skipped_configs": result.skipped,
        "timing": {
            "isam2_update_ms": percentiles(result.update_ms),
            "vo_s": result.vo_s,
            "wall_s": result.wall_s,
        },
    }


def reproduce_command(result: RunResult) -> str:
    """The command line that reproduces this run (for a scenario: from the results folder, whose
    scenario.toml holds the resolved scenario, seed included)."""
    parts = ["pancam-graph", "run"]
    if result.scenario is not None:
        parts += ["scenario.toml", "--seed", str(result.seed)]
    else:
        parts.append(result.source.path)
        flags = SourceOptions.flags()
        for key, value in result.source.options.items():
            if value is None or value is False or key not in flags:
                continue
            text = ",".join(value) if isinstance(value, tuple | list) else str(value)
            parts += [flags[key]] if value is True else [flags[key], text]
        if result.options.vo_error_model is not None:  # a scenario's is in its scenario.toml
            parts += ["--vo-error-model", result.options.vo_error_model]
    parts += ["--configs", ",".join(result.configurations)]
    if result.options.batch:
        parts.append("--batch")
    return " ".join(parts)


def _versions() -> dict[str, str]:
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for package in ("pancam-graph", "gtsam", "numpy", "opencv-python-headless", "pyproj"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            out[package] = "not installed"
    return out


def run_configuration(result: RunResult) -> dict:
    """The complete resolved configuration of a run (run.toml): source, run options, the
    configurations with their kinds, every estimator constant, the rig and versions."""
    rig, cam = result.traverse.rig, result.traverse.rig.wac
    return {
        "source": {"kind": result.source.kind, "path": result.source.path, "reference": result.source.reference,
                   "notes": list(result.source.notes),
                   "options": {k: v for k, v in result.source.options.items() if v is not None}},
        "run": {"seed": result.seed, "configs": list(result.configurations), "batch": result.options.batch,
                "command": reproduce_command(result)},
        "configurations": {name: list(c.kinds) for name, c in result.configurations.items()},
        "skipped_configurations": result.skipped,
        "estimator": result.estimator.model_dump(mode="json", exclude_none=True),
        "rig": {"name": rig.name, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                "height": cam.height, "baseline_m": rig.baseline_m, "mast_height_m": rig.mast_height_m,
                "body_T_nav_left": result.traverse.body_T_nav().matrix().tolist()},
        "stops": {"departure_s": [s.departure_s for s in result.traverse.stops]},
        "versions": _versions(),
    }
