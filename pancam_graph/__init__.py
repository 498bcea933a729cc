"""pancam_graph: rover localization over long traverses with a GTSAM factor graph.

The library is `pancam_graph.api` (also reachable from here: `pancam_graph.run(...)`); the
command line, `pancam-graph`, is a thin layer over it."""

__version__ = "0.1.0"

_API = ("run", "resume", "evaluate", "track", "simulate", "view", "analyze", "plan_sweep", "sweep", "open_data",
        "RunOutcome", "RunOptions", "SourceOptions", "RunInterrupted")


def __getattr__(name: str):
    # the API on first use: `import pancam_graph` (every worker process, `--help`) stays light
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'pancam_graph' has no attribute {name!r}")
