"""Runs a sweep's runs on a Dask cluster: one task per run, each a `pancam-graph run` process
of its own (a crash or a hang of one run cannot take a worker or the sweep with it, and a
timeout can stop it), writing its own results folder. Runs already done are skipped."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

from ..errors import ConfigError
from .spec import SweepRun

Status = Literal["done", "skipped", "failed", "timeout"]


@dataclass(frozen=True)
class RunRecord:
    """How one run of a sweep ended."""

    run: SweepRun
    status: Status
    wall_s: float
    message: str = ""


def run_one(run: SweepRun, timeout_s: float) -> RunRecord:
    """One run as its own `pancam-graph run` process (the task a worker executes)."""
    command = [sys.executable, "-m", "pancam_graph", "run", str(run.scenario_file), "--seed", str(run.seed),
               "--out", str(run.folder), "--quiet", "--no-plots", "--one-process"]
    if run.configs:
        command += ["--configs", ",".join(run.configs)]
    start = time.perf_counter()
    try:
        finished = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return RunRecord(run, "timeout", time.perf_counter() - start, f"stopped after {timeout_s:g} s")
    wall = time.perf_counter() - start
    if finished.returncode != 0:
        lines = [line for line in finished.stderr.splitlines() if line.strip()]
        why = lines[-1] if lines else f"exit {finished.returncode}"
        return RunRecord(run, "failed", wall, f"exit {finished.returncode}: {why}")
    return RunRecord(run, "done", wall)


def run_sweep(runs: list[SweepRun], timeout_s: float, workers: int = 2, scheduler: str | None = None,
              progress: Callable[[RunRecord, int, int], None] | None = None) -> list[RunRecord]:
    """Every run not done yet, on a local Dask cluster of `workers` (or the cluster at
    `scheduler`); a run that fails, crashes or times out is recorded and the others go on."""
    records = [RunRecord(r, "skipped", 0.0, "done by an earlier invocation") for r in runs if r.done]
    todo = [r for r in runs if not r.done]
    if progress is not None:
        for record in records:
            progress(record, len(records), len(runs))
    if not todo:
        return records
    with _dask_errors_only():
        return records + _run_on_dask(todo, timeout_s, workers, scheduler, len(records), len(runs), progress)


@contextmanager
def _dask_errors_only():
    """Dask logs its own shutdown races (a comm closed while the cluster closes) at INFO with a
    traceback; a run that failed is in the records, so only Dask's errors reach the terminal."""
    dask_log = logging.getLogger("distributed")
    level = dask_log.level
    dask_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        dask_log.setLevel(level)


SCHEDULER_CONNECT_S = 5.0  # a scheduler that does not answer a TCP connection in this long is not there


def check_scheduler(address: str) -> None:
    """Refuse a scheduler address that is not one (tcp://host:port) or where nothing listens,
    before anything is written: a closed port refuses at once, an unreachable host within
    SCHEDULER_CONNECT_S."""
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        protocol, location = parse_address(address, strict=True)
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"--scheduler {address!r}: not a scheduler address like tcp://host:8786 ({exc})") from None
    if protocol not in ("tcp", "tls"):
        return  # other transports (inproc, ucx) are Dask's to check
    try:
        socket.create_connection((host, port), timeout=SCHEDULER_CONNECT_S).close()
    except OSError as exc:
        raise ConfigError(f"--scheduler {address}: nothing answers there ({exc.strerror or exc})") from None


def _run_on_dask(todo: list[SweepRun], timeout_s: float, workers: int, scheduler: str | None, done: int,
                 total: int, progress: Callable[[RunRecord, int, int], None] | None) -> list[RunRecord]:
    from dask.distributed import Client, LocalCluster, as_completed

    records: list[RunRecord] = []
    if scheduler is None:
        # The tasks are processes of their own, so threads are enough to drive them.
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=False, dashboard_address=None)
    else:
        cluster = None
    try:
        client = Client(cluster if cluster is not None else scheduler, timeout="30s")
    except OSError as exc:
        raise ConfigError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    try:
        futures = {client.submit(run_one, run, timeout_s, key=f"run-{run.name}", pure=False): run for run in todo}
        for future in as_completed(futures):
            run = futures[future]
            try:
                record = future.result()
            except Exception as exc:  # the worker itself failed (killed, lost): the run is recorded
                record = RunRecord(run, "failed", 0.0, f"{type(exc).__name__}: {exc}")
            records.append(record)
            if progress is not None:
                progress(record, done + len(records), total)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return records
