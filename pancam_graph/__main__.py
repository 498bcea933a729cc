"""`python -m pancam_graph`: the console script (the sweep runs runs this way, with the
interpreter it was started with)."""

from .cli import main

main()
