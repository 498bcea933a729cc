"""Where a rerun recording goes: a spawned viewer, a file, a served gRPC endpoint or a running viewer."""

from __future__ import annotations

import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal
from urllib.parse import quote

from ..errors import ViewerUnavailable

if TYPE_CHECKING:  # rerun is imported when a recording opens: a run without one does not pay for it
    import rerun as rr

DEFAULT_VIEWER_MEMORY = "25%"  # of system RAM; the viewer drops the oldest data beyond it
GRPC_PORT, WEB_VIEWER_PORT = 9876, 9090  # rerun's own defaults: served there while they are free
SERVER_START_S = 20.0
CONNECT_TIMEOUT_S = 3.0
FLUSH_TIMEOUT_S = 15.0  # a file or viewer that has not taken a send in this long has stopped taking them
_DEFAULT_URL = f"rerun+http://127.0.0.1:{GRPC_PORT}/proxy"


@dataclass(frozen=True)
class RerunTarget:
    mode: Literal["spawn", "save", "serve", "connect"]
    path: Path | None = None  # save
    url: str | None = None  # connect
    memory_limit: str = DEFAULT_VIEWER_MEMORY  # spawn and serve
    host: str = "127.0.0.1"  # serve: the address it listens on (0.0.0.0: every interface)


@dataclass
class OpenRecording:
    stream: rr.RecordingStream
    target: RerunTarget
    served_url: str | None = None  # serve: where viewers connect (gRPC)
    viewer_url: str | None = None  # serve: the web viewer, opened on this recording
    server: subprocess.Popen | None = None  # serve: the process that holds the recording for viewers
    failure: str | None = None  # why the recording stopped; the run goes on without it

    def flush(self) -> bool:
        """Send what was logged, waiting at most FLUSH_TIMEOUT_S; False once the recording has
        failed (a full disk, a viewer that stopped reading), with the reason in `failure`. rerun
        then holds the stream: its flush, its disconnect and the process's exit would wait for
        ever, so nothing of it is touched again, and the process must end without rerun's exit
        handler (the CLI does, once everything else is written)."""
        if self.failure is not None:
            return False
        try:
            self.stream.flush(timeout_sec=FLUSH_TIMEOUT_S)
        except RuntimeError as exc:
            what = f"write {self.target.path} (a full disk?)" if self.target.mode == "save" else "reach the viewer"
            self.failure = f"rerun: the recording stopped: cannot {what}: {exc}"
        return self.failure is None

    def close(self) -> None:
        """Flush everything; a saved file gets its footer. A served recording stays served (its
        server holds it) until `stop_serving`."""
        if self.flush() and self.target.mode == "save":
            self.stream.disconnect()

    @property
    def serving(self) -> bool:
        return self.server is not None and self.server.poll() is None

    def stop_serving(self) -> None:
        if self.server is None:
            return
        self.stream.disconnect()  # first: a stream left on a stopped server complains at exit
        if self.server.poll() is None:
            self.server.terminate()
            try:
                self.server.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.server.kill()


def open_recording(target: RerunTarget, name: str, on_viewer: Callable[[str], None] | None = None) -> OpenRecording:
    """The recording stream to `target`; a served one's web viewer address goes to `on_viewer`
    as soon as it is up."""
    import rerun as rr

    from .rerun_scene import APP_ID

    stream = rr.RecordingStream(APP_ID, recording_id=str(uuid.uuid4()))
    stream.send_recording_name(name)
    served = viewer = server = None
    try:
        if target.mode == "save":
            target.path.parent.mkdir(parents=True, exist_ok=True)
            stream.save(target.path)
        elif target.mode == "spawn":
            # the module-level spawn: RecordingStream.spawn cannot name the executable
            rr.spawn(memory_limit=target.memory_limit, executable_path=_viewer_executable(), recording=stream)
        elif target.mode == "serve":
            server, grpc_port, served, viewer = _start_server(target)
            stream.connect_grpc(f"rerun+http://{_local(target.host)}:{grpc_port}/proxy")
        else:
            _check_listening(target.url)
            stream.connect_grpc(target.url)
    except (OSError, RuntimeError) as exc:
        where = target.path or target.url or target.mode
        raise ViewerUnavailable(f"rerun: cannot open the recording ({where}): {exc}") from None
    if viewer is not None and on_viewer is not None:
        on_viewer(viewer)
    return OpenRecording(stream, target, served, viewer, server)


def _start_server(target: RerunTarget) -> tuple[subprocess.Popen, int, str, str]:
    """rerun's gRPC server and web viewer in a process of their own, listening on the target's
    address only (the SDK's in-process server listens on every interface); it lives on after the
    run, so a viewer can still open the recording, and dies with this process. Returns the
    process, its gRPC port, the recording's gRPC URL and the web viewer's URL opened on the
    recording (the page needs the recording's address in ?url=, or it opens on rerun's welcome
    screen)."""
    grpc_port, web_port = _free_port(target.host, GRPC_PORT), _free_port(target.host, WEB_VIEWER_PORT)
    command = [_server_executable(), "--serve-web", "--bind", target.host, "--port", str(grpc_port),
               "--web-viewer-port", str(web_port), "--server-memory-limit", target.memory_limit]
    log = tempfile.TemporaryFile()
    server = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log,
                              preexec_fn=_die_with_parent if sys.platform == "linux" else None)
    deadline = time.monotonic() + SERVER_START_S
    while any(_refused(_local(target.host), port, 0.5) for port in (grpc_port, web_port)):
        if server.poll() is not None or time.monotonic() > deadline:
            server.kill()
            log.seek(0)
            said = log.read().decode(errors="replace").strip().splitlines()
            raise ViewerUnavailable(f"rerun: the web viewer did not start ({' '.join(command)}): "
                                    f"{said[-1] if said else 'no message'}")
        time.sleep(0.1)
    shown = socket.getfqdn() if target.host in ("0.0.0.0", "::") else target.host
    served = f"rerun+http://{shown}:{grpc_port}/proxy"
    return server, grpc_port, served, f"http://{shown}:{web_port}/?url={quote(served, safe='')}"


def _free_port(host: str, preferred: int) -> int:
    """The preferred port when nothing listens there, else one the system picks."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            try:
                probe.bind((host, port))
            except OSError:
                continue
            return probe.getsockname()[1]
    raise ViewerUnavailable(f"rerun: cannot listen on {host}")


def _local(host: str) -> str:
    """How this machine reaches a server listening on `host`."""
    return "127.0.0.1" if host in ("0.0.0.0", "::") else host


def _refused(host: str, port: int, timeout_s: float) -> OSError | None:
    """Why nothing accepts a connection at host:port, or None when something does."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return None
    except OSError as exc:
        return exc


def _die_with_parent() -> None:
    """In the server process, before it starts: Linux ends it when the run's process ends."""
    import ctypes
    import signal

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _check_listening(url: str | None) -> None:
    """A viewer that does not answer would make every flush, and the process's exit, wait
    forever (rerun's gRPC client waits without a limit): find out first. A rerun viewer speaks
    gRPC, so it answers HTTP/2's connection preface with its SETTINGS; a listener that never
    answers, or a server of another protocol, does not."""
    from urllib.parse import urlparse

    parsed = urlparse((url or _DEFAULT_URL).replace("rerun+", "", 1))
    host, port = parsed.hostname or "127.0.0.1", parsed.port or GRPC_PORT
    try:
        with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S) as connection:
            connection.sendall(_HTTP2_PREFACE + _HTTP2_EMPTY_SETTINGS)
            reply = connection.recv(64)  # a frame header first: length (3 bytes), type, flags, stream
    except TimeoutError:
        raise ViewerUnavailable(f"rerun: {host}:{port} accepts connections but does not answer within "
                                f"{CONNECT_TIMEOUT_S:g} s: not a rerun viewer, or a stalled one") from None
    except OSError as exc:
        raise ViewerUnavailable(f"rerun: no viewer answers at {host}:{port} ({exc.strerror or exc})") from None
    if len(reply) < 4 or reply[3] != _HTTP2_SETTINGS:
        said = reply.decode("latin-1").strip().splitlines()[0][:60] if reply.strip() else "it closed the connection"
        raise ViewerUnavailable(f"rerun: {host}:{port} is not a rerun viewer (it answered {said!r}, not gRPC)")


_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
_HTTP2_SETTINGS = 0x4
_HTTP2_EMPTY_SETTINGS = bytes([0, 0, 0, _HTTP2_SETTINGS, 0, 0, 0, 0, 0])


def _server_executable() -> str:
    """rerun's own binary (the `rerun` script starts it as a child, which would outlive us)."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    binary = None if spec is None or spec.origin is None else Path(spec.origin).parent / "rerun"
    return str(binary) if binary is not None and binary.exists() else (_viewer_executable() or "rerun")


def _viewer_executable() -> str | None:
    """The `rerun` viewer installed beside this Python, found even when the venv is not on PATH."""
    candidate = Path(sys.executable).parent / "rerun"
    return str(candidate) if candidate.exists() else None
