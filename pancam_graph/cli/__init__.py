"""Command line: parses arguments into library calls (api.py, bench.py), prints what they return
and chooses exit codes, one module per group of commands (app.py holds the app and its one error
handler)."""

from . import inputs, run, studies  # noqa: F401  (their commands register on the app)
from .app import app, main

__all__ = ["app", "main"]
