"""How a rectified stereo pair's small calibration error moves its pixels, to first order.

A pair is calibrated once, on the ground; what is left of its error is the same in every frame.
Its six terms, c = (w_x, w_y, w_z, e, s, b): the right camera turned by a small rotation w (rad,
in the left camera's axes), its focal length off by a further ratio e, both focal lengths off by
a ratio s, and the baseline off by a ratio b. They move a stereo observation (u_left, u_right, v)
by

    du_left = s (u_left - cx),   dv = s (v - cy),
    du_right = s (u_right - cx) + f (w_x x y - w_y (1 + x^2) + w_z y + e x) + b (u_right - u_left),
    x, y = (u_right - cx, v - cy) / f

(sim/errors.py's TrueRig is that error exactly; this is its first order, within 0.002 px of it
over the WAC's image at 2-40 m: tests/kinds/test_stereo_calibration.py). About the vertical (w_y)
it is a disparity bias of f w_y (0.3 px for 0.01 deg on the WAC) that scales every range by
(1 + Z w_y / B): a range error growing with the range. The baseline's own error b scales every
range alike.
"""

from __future__ import annotations

import numpy as np

NAMES = ("right_rotation_x_rad", "right_rotation_y_rad", "right_rotation_z_rad", "right_focal_ratio", "focal_scale",
         "baseline_scale")


def pixel_shifts(uvv: np.ndarray, focal_px: float, cx: float, cy: float) -> np.ndarray:
    """d (u_left, u_right, v) / d c at measured observations: (3, 6) for one (3,), (N, 3, 6) for (N, 3)."""
    uvv = np.asarray(uvv, dtype=float)
    one = uvv.ndim == 1
    uvv = np.atleast_2d(uvv)
    u_left, u_right, v = uvv[:, 0], uvv[:, 1], uvv[:, 2]
    x, y = (u_right - cx) / focal_px, (v - cy) / focal_px
    shifts = np.zeros((len(uvv), 3, len(NAMES)))
    shifts[:, 0, 4] = u_left - cx
    shifts[:, 1] = np.column_stack([focal_px * x * y, -focal_px * (1.0 + x * x), focal_px * y, focal_px * x,
                                    u_right - cx, u_right - u_left])
    shifts[:, 2, 4] = v - cy
    return shifts[0] if one else shifts
