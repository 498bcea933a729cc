"""A `pancam-graph run ... --rerun serve` started as a user would, and the URL it prints."""

import subprocess
import sys
from pathlib import Path


def serve_run(*args: str) -> tuple[subprocess.Popen, str]:
    """Start `pancam-graph run ARGS --rerun serve`; return the process once it has printed the
    web viewer's URL, and that URL exactly as printed."""
    exe = Path(sys.executable).parent / "pancam-graph"
    run = subprocess.Popen([str(exe), "run", *args, "--no-plots", "--quiet", "--rerun", "serve"],
                           stderr=subprocess.PIPE, text=True)
    said = ""
    while "web viewer at" not in said:
        line = run.stderr.readline()
        if not line:
            run.kill()
            raise AssertionError(f"no web viewer URL before the run ended: {said}")
        said += line
    return run, said.split("web viewer at ", 1)[1].split()[0]
