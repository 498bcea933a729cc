"""Where a rerun recording goes: a spawned viewer, a file, a served gRPC endpoint or a running viewer."""

from __future__ import annotations

import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Literal
from urllib.parse import quote

import rerun as rr

from ..errors import ResultsError, ViewerUnavailable
from .rerun_scene import APP_ID

DEFAULT_VIEWER_MEMORY = "25%"  # of system RAM; the viewer drops the oldest data beyond it


@dataclass(frozen=True)
class RerunTarget:
    mode: Literal["spawn", "save", "serve", "connect"]
    path: Path | None = None  # save
    url: str | None = None  # connect
    memory_limit: str = DEFAULT_VIEWER_MEMORY  # spawn and serve


@dataclass
class OpenRecording:
    stream: rr.RecordingStream
    target: RerunTarget
    served_url: str | None = None  # serve: where viewers connect (gRPC)
    viewer_url: str | None = None  # serve: the web viewer, opened on this recording


    def close(self) -> None:
        """Flush everything; a saved file gets its footer."""
        self.stream.flush()
        if self.target.mode == "save":
            self.stream.disconnect()


def open_recording(target: RerunTarget, name: str) -> OpenRecording:
    stream = rr.RecordingStream(APP_ID, recording_id=str(uuid.uuid4()))
    stream.send_recording_name(name)
    served = None
    try:
        if target.mode == "save":
            target.path.parent.mkdir(parents=True, exist_ok=True)
            stream.save(target.path)
        elif target.mode == "spawn":
            # the module-level spawn: RecordingStream.spawn cannot name the executable
            rr.spawn(memory_limit=target.memory_limit, executable_path=_viewer_executable(), recording=stream)
        elif target.mode == "serve":
            served = stream.serve_grpc(server_memory_limit=target.memory_limit)
            # the web viewer from the start, so the run is watched as it solves; its page needs
            # the recording's address in ?url=, or it opens on rerun's welcome screen
            rr.serve_web_viewer(web_port=WEB_VIEWER_PORT, open_browser=False, connect_to=served)
        else:
            _check_listening(target.url)
            stream.connect_grpc(target.url)
    except (OSError, RuntimeError) as exc:
        where = target.path or target.url or target.mode
        raise ResultsError(f"rerun: cannot open the recording ({where}): {exc}") from None
    viewer = None if served is None else f"http://localhost:{WEB_VIEWER_PORT}/?url={quote(served, safe='')}"
    return OpenRecording(stream, target, served, viewer)


WEB_VIEWER_PORT = 9090
CONNECT_TIMEOUT_S = 3.0
_DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"


def _check_listening(url: str | None) -> None:
    """A viewer that does not listen would make every flush wait forever: find out first."""
    import socket
    from urllib.parse import urlparse

    parsed = urlparse((url or _DEFAULT_URL).replace("rerun+", "", 1))
    host, port = parsed.hostname or "127.0.0.1", parsed.port or 9876
    try:
        with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise ViewerUnavailable(f"rerun: no viewer answers at {host}:{port} ({exc.strerror or exc})") from None


def _viewer_executable() -> str | None:
    """The `rerun` viewer installed beside this Python, found even when the venv is not on PATH."""
    candidate = Path(sys.executable).parent / "rerun"
    return str(candidate) if candidate.exists() else None
