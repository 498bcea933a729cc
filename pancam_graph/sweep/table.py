"""The reducer: every run folder's metrics.json into one table of runs, and a summary per
scenario, rig, variant and configuration (evo_res's idea)."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import ResultsError
from ..evaluation.consistency import Consistency, monte_carlo_summary
from .runner import RunRecord

RUN_COLUMNS = ("scenario", "rig", "variant", "seed", "config", "relative_closure_pct", "ate_rmse_m",
               "drift_translation_pct", "rmse_m", "crlb_rms_m", "efficiency", "anees", "nees_last", "wall_s")


@dataclass(frozen=True)
class ConfigSummary:
    """One configuration of one scenario, rig and variant over the sweep's seeds."""

    scenario: str
    rig: str
    variant: str
    config: str
    runs: int
    closure_pct_mean: float
    closure_pct_max: float
    ate_m_mean: float
    efficiency: float | None  # sqrt(mean RMSE^2 / mean CRLB^2) over runs, as bench --monte-carlo
    anees: float | None
    anees_band: tuple[float, float] | None
    covariance: str  # consistent / over-confident / under-confident / "" without truth
    # the last stop's NEES / 3, mean over the runs, against the exact band of independent runs
    nees_last: float | None = None
    last_stop_covariance: str = ""


def run_rows(records: list[RunRecord]) -> list[dict]:
    """One row per configuration of every finished run, read back from its metrics.json."""
    rows = []
    for record in records:
        if record.status not in ("done", "skipped"):
            continue
        path = record.run.folder / "metrics.json"
        try:
            document = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ResultsError(f"{path}: cannot read the run's metrics: {exc}") from None
        wall = document.get("timing", {}).get("wall_s")
        for config, m in document["configs"].items():
            rows.append({"scenario": record.run.scenario, "rig": record.run.rig, "variant": record.run.variant,
                         "seed": record.run.seed, "config": config, "wall_s": wall,
                         **{c: m.get(c) for c in RUN_COLUMNS if c in m}})
    return rows


def summarize(rows: list[dict]) -> list[ConfigSummary]:
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scenario"], row["rig"], row["variant"], row["config"]), []).append(row)
    out = []
    for (scenario, rig, variant, config), group in sorted(groups.items()):
        closure = [r["relative_closure_pct"] for r in group if r.get("relative_closure_pct") is not None]
        ate = [r["ate_rmse_m"] for r in group if r.get("ate_rmse_m") is not None]
        mc = monte_carlo(group)
        at_end = mc["last_stop"] if mc else None
        out.append(ConfigSummary(
            scenario, rig, variant, config, len(group),
            float(np.mean(closure)) if closure else float("nan"), float(np.max(closure)) if closure else float("nan"),
            float(np.mean(ate)) if ate else float("nan"),
            mc["efficiency"] if mc else None, mc["anees"] if mc else None,
            tuple(mc["anees_band"]) if mc else None, mc["covariance"] if mc else "",
            at_end["nees_last"] if at_end else None, at_end["covariance"] if at_end else ""))
    return out


def monte_carlo(rows: list[dict]) -> dict | None:
    """bench --monte-carlo's summary of one configuration's runs, the last stop's NEES over them
    too; None unless every run has truth (efficiency and ANEES need it)."""
    consistency = [Consistency(r["rmse_m"], r["crlb_rms_m"], r["efficiency"], r["anees"], (0.0, 0.0))
                   for r in rows if r.get("anees") is not None and r.get("crlb_rms_m") is not None]
    if not rows or len(consistency) != len(rows) or any(r.get("nees_last") is None for r in rows):
        return None
    return monte_carlo_summary(consistency, [r["nees_last"] for r in rows])


def write_tables(out: Path, records: list[RunRecord], rows: list[dict], summary: list[ConfigSummary]) -> None:
    """runs.csv (a row per run and configuration), summary.csv and runs_status.csv (every run,
    with how it ended) in the sweep folder."""
    with (out / "runs.csv").open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, RUN_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    with (out / "summary.csv").open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow([fl.name for fl in fields(ConfigSummary)])
        for s in summary:
            writer.writerow([getattr(s, fl.name) for fl in fields(ConfigSummary)])
    with (out / "runs_status.csv").open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["run", "status", "wall_s", "message"])
        for r in sorted(records, key=lambda r: r.run.name):
            writer.writerow([r.run.name, r.status, f"{r.wall_s:.1f}", r.message])
