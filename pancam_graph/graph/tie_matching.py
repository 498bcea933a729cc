"""The image matcher's tie points between two sites, as measured against the renderer's truth:
how many it finds, how far off they are and how many are near misses, by the distance between
the two sites. The simulator draws its ties from it (sim/errors.py); the sites' estimator
weights a tie's views by it (noise.stereo_tie)."""

from __future__ import annotations

import numpy as np

# `pancam-graph bench sites` on denver_trail seeds 0 and 1 (49 site pairs, 1,913 ties;
# docs/simulation_errors.md), by the distance between the two sites (m): the medians of the
# pairs 28-34, 34-42, 42-52 and 52-58 m apart, linear between: the count of a pair (none from
# 59.9 m on: 10 pairs), the median error of a tie (px) and the share of ties beyond 3 px.
DISTANCE_M = (31.3, 37.8, 48.8, 55.9, 59.9)
COUNT = (130.0, 51.0, 33.0, 11.0, 0.0)
MEDIAN_ERROR_PX = (0.37, 0.44, 0.69, 1.12, 1.12)
NEAR_MISS_SHARE = (0.034, 0.006, 0.045, 0.102, 0.102)
NEAR_MISS_PX = (3.0, 10.0)  # how far a near miss is (uniform: the bench does not resolve the tail past 3 px)
MEDIAN_RADIUS = np.sqrt(2.0 * np.log(2.0))  # a 2-D Gaussian's median radius, in sigmas


def count(distance_m: float) -> float:
    """The matcher's median count of ties between two sites this far apart."""
    return float(np.interp(distance_m, DISTANCE_M, COUNT, right=0.0))


def near_miss_share(distance_m: float) -> float:
    """The share of a site pair's ties that are near misses (3-10 px off)."""
    return float(np.interp(distance_m, DISTANCE_M, NEAR_MISS_SHARE))


def sigma_px(distance_m: float) -> float:
    """A tie's matching error per image axis (px, 1 sigma) between sites this far apart, near
    misses aside: the measured median radius as a 2-D Gaussian's."""
    return float(np.interp(distance_m, DISTANCE_M, MEDIAN_ERROR_PX) / MEDIAN_RADIUS)
