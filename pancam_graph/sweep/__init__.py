"""Sweeps: many runs (scenarios x rigs x estimator variants x seeds) on a Dask cluster, one
task per run, each writing its own results folder, and a reducer that reads their metrics
into one table."""
