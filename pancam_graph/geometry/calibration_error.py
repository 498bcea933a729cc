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
    """d (u_left, u_right, v) / d c at observations uvv: (3, 6) for one (3,), (N, 3, 6) for (N, 3).

    A site view's factor takes them at its predicted pixels, not at the measured ones: a measured
    pixel's noise is in the coefficients and in the residual alike, and the two together pull c
    one way whatever its truth (the baseline's term, (u_right - u_left), takes the right pixel's
    noise once more: -sigma^2 of gradient for every view). The two-stop adjustment's sensitivity
    takes them at the measured pixels: over 400 drawn steps the VO factor's gradient on c at the
    truth was the same with the fitted pixels and within its standard error of zero."""
    uvv = np.asarray(uvv, dtype=float)
    if uvv.ndim == 1:  # plain floats: a site view's factor takes them at every evaluation
        (u_left, u_right, v), zero = uvv.tolist(), 0.0
    else:
        u_left, u_right, v = uvv[..., 0], uvv[..., 1], uvv[..., 2]
        zero = np.zeros_like(u_left)
    x, y = (u_right - cx) / focal_px, (v - cy) / focal_px
    shifts = np.array([[zero, zero, zero, zero, u_left - cx, zero],
                       [focal_px * x * y, -focal_px * (1.0 + x * x), focal_px * y, focal_px * x, u_right - cx,
                        u_right - u_left],
                       [zero, zero, zero, zero, v - cy, zero]])
    return shifts if uvv.ndim == 1 else np.moveaxis(shifts, (0, 1), (-2, -1))


def pixel_shift_derivative(uvv: np.ndarray, c: np.ndarray, focal_px: float, cx: float, cy: float) -> np.ndarray:
    """d (pixel_shifts(uvv) @ c) / d uvv (3 x 3) at one observation: how the shift the error c
    makes moves with the pixel it is taken at."""
    w_x, w_y, w_z, e, s, b = c.tolist()
    x, y = (float(uvv[1]) - cx) / focal_px, (float(uvv[2]) - cy) / focal_px
    return np.array([[s, 0.0, 0.0],
                     [-b, w_x * y - 2.0 * w_y * x + e + s + b, w_x * x + w_z],
                     [0.0, 0.0, s]])
