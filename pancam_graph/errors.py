"""Typed errors of the package: one base class, one subclass per area.

Library code raises these; only the CLI turns them into messages and exit codes.
"""

from __future__ import annotations

from pathlib import Path


class PancamGraphError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(PancamGraphError):
    """A scenario or configuration file is missing, malformed or out of range."""


class InputError(PancamGraphError):
    """A recorded input (bag, GPS log, calibration, observation file) is missing, malformed or
    truncated; the message names the file and the line, record or field."""


class FrameError(InputError):
    """An image of one stop could not be used and the run stops there; `partial` keeps what the
    front-end did before it (the source's data for the stops before, or None)."""

    def __init__(self, message: str, stop: int, partial: object | None = None):
        super().__init__(message)
        self.stop = stop
        self.partial = partial


class GeodesyError(PancamGraphError):
    """A coordinate conversion got invalid input (non-finite, out of range)."""


class ProcessDied(PancamGraphError):
    """A call in a process apart (`runtime.processes.call_apart`) ended without an answer: the
    process was killed, ran out of memory, or crashed inside a library."""


class FrontendError(PancamGraphError):
    """Observations could not be turned into measurements (e.g. malformed arrays)."""


class GraphError(PancamGraphError):
    """The factor graph is ill-posed or the smoother failed."""


class EvaluationError(PancamGraphError):
    """Two trajectories cannot be compared (nothing matches in time, counts differ)."""


class ResultsError(PancamGraphError):
    """A results folder cannot be written or read."""


class FolderInUse(ResultsError):
    """Another run owns the results folder (a usage error: choose another --out)."""


class WriteFailed(ResultsError):
    """A file could not be written (a full disk, a permission): never the input's fault."""


class ViewerUnavailable(ResultsError):
    """The rerun recording cannot be made: no viewer answers, or its file cannot be written.
    A run goes on without it."""


class RunInterrupted(PancamGraphError):
    """Ctrl-C stopped a run; what was done is in `partial`, and a resume goes on from
    `resume_stop` (None: no checkpoint was saved yet)."""

    def __init__(self, partial: Path, resume_stop: int | None):
        goes_on = (f"`pancam-graph run --resume {partial}` goes on from stop {resume_stop}" if resume_stop is not None
                   else "no checkpoint was saved yet")
        super().__init__(f"what was done is in {partial}; {goes_on}")
        self.partial = partial
        self.resume_stop = resume_stop

