"""A script that runs the package on several cores from its top level, outside `if __name__ ==
"__main__":`, is refused at once in one line saying what to add, with nothing written (its
worker processes would import it again and break the pool); the guarded script passes."""

import subprocess
import sys
import textwrap


def _script(tmp_path, body: str) -> subprocess.CompletedProcess:
    script = tmp_path / "example.py"
    script.write_text(textwrap.dedent(body))
    return subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=300)


def test_an_unguarded_script_is_refused_before_anything_is_written(tmp_path):
    done = _script(tmp_path, """
        import pancam_graph
        outcome = pancam_graph.run("denver_trail", seed=0, out="results/denver", figures=False, processes=2)
    """)
    assert done.returncode == 1
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("pancam_graph.errors.ConfigError: ") and "example.py:3" in last
    assert 'put the call under `if __name__ == "__main__":`' in last
    assert "BrokenProcessPool" not in done.stderr and "bootstrapping" not in done.stderr
    assert not (tmp_path / "results").exists()


def test_a_guarded_script_or_one_process_passes_the_check(tmp_path):
    done = _script(tmp_path, """
        from pancam_graph.api import check_script_guard
        from pancam_graph.runtime.processes import unguarded_script_call

        print("top level:", unguarded_script_call())
        if __name__ == "__main__":
            check_script_guard()
            print("guarded:", unguarded_script_call())
    """)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("top level: ") and lines[0].endswith("example.py:5")
    assert lines[1] == "guarded: None"
