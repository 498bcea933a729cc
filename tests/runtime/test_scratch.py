"""The temporary folders of processes that were killed are removed by the next run, and only
theirs."""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from pancam_graph.runtime import scratch


def test_the_folders_of_killed_processes_are_swept(tmp_path):
    # a process that made a folder and was killed before it could remove it
    child = subprocess.run([sys.executable, "-c", "import os, tempfile, sys\n"
                            "from pancam_graph.runtime import scratch\n"
                            f"tempfile.tempdir = {str(tmp_path)!r}\n"
                            "folder = scratch.temporary_folder('log')\n"
                            "print(folder.name, flush=True)\n"
                            "os._exit(0)"], capture_output=True, text=True, check=True)
    left = Path(child.stdout.strip())
    assert left.is_dir() and left.parent == tmp_path
    ours = Path(tempfile.mkdtemp(prefix=f"{scratch.PREFIX}log-{scratch._host()}-{os.getpid()}-", dir=tmp_path))
    elsewhere = Path(tempfile.mkdtemp(prefix=f"{scratch.PREFIX}log-otherhost-{2**22 + 1}-", dir=tmp_path))
    not_ours = tmp_path / "pancam-graph-results"
    not_ours.mkdir()
    (not_ours / "keep").touch()
    link = tmp_path / f"{left.name[:-3]}xyz"  # a dead process's name, a link to another folder
    link.symlink_to(not_ours)
    assert scratch.sweep(tmp_path) == [left]
    assert not left.exists() and ours.is_dir() and elsewhere.is_dir() and (not_ours / "keep").is_file()
    assert link.is_symlink()
