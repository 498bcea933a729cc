"""The run's temporary folders: named after the host and the process that made them, so that the
first folder a process makes removes those of this host's processes that no longer run (a run
killed with SIGKILL, or out of memory, cannot remove its own: /tmp held hundreds of them)."""

from __future__ import annotations

import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

PREFIX = "pancam-graph-"
# pancam-graph-<what>-<host>-<pid>-<tempfile's random part, which has no "-">
_NAME = re.compile(rf"^{PREFIX}[a-z]+-(?P<host>.+)-(?P<pid>\d+)-[^-]+$")
_swept_in: int | None = None  # the process that swept (a forked one sweeps again)


def temporary_folder(what: str) -> tempfile.TemporaryDirectory:
    """A new temporary folder for this process's `what` (a word: "log", "groups"), removed with
    the returned object; the system's temporary folder holds it (TMPDIR chooses another)."""
    global _swept_in
    if _swept_in != os.getpid():
        _swept_in = os.getpid()
        sweep()
    return tempfile.TemporaryDirectory(prefix=f"{PREFIX}{what}-{_host()}-{os.getpid()}-", ignore_cleanup_errors=True)


def sweep(where: Path | None = None) -> list[Path]:
    """Remove the folders in `where` (the system's temporary folder) that this host's processes
    made and left when they ended without removing them; those of running processes and of other
    hosts stay. Returns the folders removed."""
    if os.name != "posix":  # no signal 0 to ask whether a process runs
        return []
    removed = []
    for path in Path(where or tempfile.gettempdir()).glob(f"{PREFIX}*"):
        match = _NAME.match(path.name)
        if (match is None or match["host"] != _host() or _running(int(match["pid"])) or path.is_symlink()
                or not path.is_dir()):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname()) or "host"


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True
