"""`python -m pancam_graph`: the console script (the sweep runs runs this way, with the
interpreter it was started with)."""

from .cli import main

if __name__ == "__main__":  # not when a worker process imports it again (frontend/vo_ahead.py)
    main()
