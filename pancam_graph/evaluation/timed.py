"""A stop-by-stop trajectory at any time: standing still from a stop's time to its departure,
then moving geodesically (SE(3)) to the next stop."""

from __future__ import annotations

import gtsam
import numpy as np


def poses_at_times(stop_times_s: np.ndarray, departures_s: np.ndarray, world_T_body: np.ndarray,
                   times_s: np.ndarray) -> np.ndarray:
    """world_T_body (M, 4, 4) at `times_s`; times outside the stops' span take the nearest end."""
    out = np.zeros((len(times_s), 4, 4))
    k_of = np.clip(np.searchsorted(stop_times_s, times_s, side="right") - 1, 0, len(stop_times_s) - 1)
    for i, (t, k) in enumerate(zip(times_s, k_of, strict=True)):
        if t <= departures_s[k] or k + 1 == len(stop_times_s):
            out[i] = world_T_body[k]
            continue
        a = (t - departures_s[k]) / (stop_times_s[k + 1] - departures_s[k])
        out[i] = gtsam.Pose3(world_T_body[k]).slerp(float(np.clip(a, 0.0, 1.0)),
                                                     gtsam.Pose3(world_T_body[k + 1])).matrix()
    return out
