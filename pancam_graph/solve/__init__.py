"""Solving a traverse: the localizer (one configuration, one stop at a time), a group of
configurations stepped through the stops, groups side by side in worker processes, and the
run's typed results."""
