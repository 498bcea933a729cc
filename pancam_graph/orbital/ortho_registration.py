"""A site's ground from above (its panorama's dense stereo, records.GroundPatch) found in an
orbital orthoimage: where the map's image puts the rover.

The patch's cells are carried into the map by the predicted pose and averaged into the
orthoimage's own pixels: a template of the ground as the orbiter would see it, with a mask of
the pixels the rover saw. OpenCV's normalized cross-correlation (matchTemplate,
TM_CCOEFF_NORMED, masked) over the prediction's search window finds the shift; a parabola
through the peak and its neighbours gives it to a fraction of a pixel. The orthoimage is lit by
another sun than the rover's images, which the normalization takes out as far as it is a
change of gain and offset.

The covariance is the least-squares one of the images' difference at the peak (2 (1 - peak) of
the normalized grey levels per pixel, over the peak's curvature and the pixels the template
has), with the pixels counted in blocks of `correlated_pixels`: neither image's grey levels are
independent from one pixel to the next (the orthoimage's pixel integrates the ground, the
patch's cells average many rover pixels). That alone was too small by a factor of 2-3 in
variance from one site to the next; a floor of `floor_m` per axis covers what it misses. A
place more than `_DISTINCT_M` from the peak that correlates nearly as well makes the site
ambiguous: refused, not averaged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from pyproj import CRS

from ..geometry.geodesy import LocalFrame
from ..records import GroundPatch, MapRaster
from .dem_registration import MapNotCovering, RegistrationFailed
from .maps import ground_spacing

_DISTINCT_M = 3.0  # a peak this far from the best one is another place (the ground's texture is 1-4 m)


@dataclass(frozen=True)
class OrthoSettings:
    """What a correlation must show to be used, and how its pixels are counted."""

    min_pixels: int = 400  # template pixels the rover saw (0.5 m pixels: 100 m^2)
    min_peak: float = 0.2  # normalized correlation at the peak
    min_margin: float = 0.05  # by which the peak must beat any other place over 3 m away
    correlated_pixels: float = 6.0  # template pixels per independent sample (the module docstring)
    # per axis, in quadrature: the error the peak's curvature does not see (the two suns' shading of
    # the relief, the template's gridding). correlated_pixels and floor_m were set on mars_excerpt
    # seeds 4000 and 4002's rendered sites (docs/orbital.md, "The orthoimage")
    floor_m: float = 0.2
    min_samples: int = 4  # rover pixels a template pixel must average


@dataclass(frozen=True)
class OrthoRegistration:
    """The rover's horizontal position in the map's frame at a site, from its ground patch
    against the map's orthoimage."""

    measurement: np.ndarray  # (east, north) of the body, local ENU as the map has it
    covariance: np.ndarray  # (2, 2)
    peak: float  # normalized correlation
    margin: float  # peak minus the best correlation elsewhere
    pixels: int  # template pixels used
    seconds: float


def template(patch: GroundPatch, map_T_body: np.ndarray, orthoimage: MapRaster, frame: LocalFrame,
             min_samples: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The patch seen as the orthoimage: (grey, mask) on the orthoimage's pixel grid and the
    (row, col) of their upper-left pixel in it, with the patch carried by `map_T_body`."""
    enu = patch.points_body.astype(float) @ map_T_body[:3, :3].T + map_T_body[:3, 3]
    xy = frame.to_map(enu, CRS.from_wkt(orthoimage.crs_wkt))
    col = np.floor((xy[:, 0] - orthoimage.x0_m) / orthoimage.post_m).astype(np.int64)
    row = np.floor((orthoimage.y0_m - xy[:, 1]) / orthoimage.post_m).astype(np.int64)
    r0, c0 = row.min(), col.min()
    shape = (int(row.max() - r0 + 1), int(col.max() - c0 + 1))
    flat = (row - r0) * shape[1] + (col - c0)
    size = shape[0] * shape[1]
    samples = np.bincount(flat, patch.samples.astype(float), size)
    grey = np.bincount(flat, patch.grey * patch.samples, size) / np.maximum(samples, 1.0)
    mask = samples >= min_samples
    return grey.reshape(shape).astype(np.float32), mask.reshape(shape), int(r0), int(c0)


def register_patch(patch: GroundPatch, map_T_body: np.ndarray, orthoimage: MapRaster, frame: LocalFrame,
                   search_m: float, settings: OrthoSettings = OrthoSettings()) -> OrthoRegistration:
    """Where the orthoimage puts the body: its position as `map_T_body` (4x4, the predicted pose
    in the map's frame) would have it, moved by the shift that best correlates the patch with
    the orthoimage within `search_m`. RegistrationFailed (MapNotCovering) when it cannot say."""
    started = time.perf_counter()
    grey, mask, r0, c0 = template(patch, map_T_body, orthoimage, frame, settings.min_samples)
    pixels = int(mask.sum())
    if pixels < settings.min_pixels:
        raise RegistrationFailed(f"the ground patch covers {pixels} orthoimage pixels, fewer than "
                                 f"{settings.min_pixels}")
    east_m, north_m = ground_spacing(orthoimage)  # a pixel's size on the ground
    pad_x, pad_y = int(np.ceil(search_m / east_m)), int(np.ceil(search_m / north_m))
    rows, cols = orthoimage.values.shape
    top, left = r0 - pad_y, c0 - pad_x
    bottom, right = r0 + grey.shape[0] + pad_y, c0 + grey.shape[1] + pad_x
    if top < 0 or left < 0 or bottom > rows or right > cols:
        raise MapNotCovering("the orthoimage does not reach round the site")
    window = orthoimage.values[top:bottom, left:right].astype(np.float32)
    if np.any(window[pad_y:pad_y + grey.shape[0], pad_x:pad_x + grey.shape[1]][mask] == 0):
        raise RegistrationFailed("the orthoimage has no data under the site (grey level 0)")
    score = cv2.matchTemplate(window, grey, cv2.TM_CCOEFF_NORMED, mask=mask.astype(np.float32))
    score = np.nan_to_num(score, nan=-1.0, posinf=-1.0, neginf=-1.0)
    y, x = np.unravel_index(int(np.argmax(score)), score.shape)
    peak = float(score[y, x])
    yy, xx = np.mgrid[:score.shape[0], :score.shape[1]]
    far = np.hypot((yy - y) * north_m, (xx - x) * east_m) > _DISTINCT_M
    margin = peak - float(score[far].max()) if far.any() else 1.0
    if peak < settings.min_peak:
        raise RegistrationFailed(f"the ground patch does not correlate with the orthoimage (peak {peak:.2f}, "
                                 f"{settings.min_peak:.2f} needed)")
    if margin < settings.min_margin:
        raise RegistrationFailed(f"the ground patch is ambiguous in the orthoimage: another place over "
                                 f"{_DISTINCT_M:g} m away correlates nearly as well ({margin:.2f} less, "
                                 f"{settings.min_margin:.2f} needed)")
    if not (0 < y < score.shape[0] - 1 and 0 < x < score.shape[1] - 1):
        raise RegistrationFailed(f"the best correlation is at the edge of the {search_m:.1f} m search")
    dx, dy = peak_offset(score, x, y)
    shift_px = np.array([x + dx - pad_x, y + dy - pad_y])  # columns east, rows south
    curvature = _curvature(score, x, y) / orthoimage.post_m**2  # per m^2
    independent = pixels / settings.correlated_pixels
    residual = max(2.0 * (1.0 - peak), 1e-3)  # per pixel, normalized grey levels
    try:
        covariance_map = residual / independent * np.linalg.inv(curvature)
    except np.linalg.LinAlgError:
        raise RegistrationFailed("the correlation peak is flat in some direction") from None
    if np.any(np.linalg.eigvalsh(covariance_map) <= 0):
        raise RegistrationFailed("the correlation peak is not a maximum")
    # the shift in map coordinates, taken to the map's local ENU at the body
    crs = CRS.from_wkt(orthoimage.crs_wkt)
    body = map_T_body[:3, 3]
    at = frame.to_map(body[None, :], crs)[0]
    moved = at + np.array([shift_px[0], -shift_px[1]]) * orthoimage.post_m
    height = frame.to_geodetic(body[None, :])[0, 2]  # a map point's ENU depends on its height
    enu = frame.from_map(np.vstack([at, moved, at + [1.0, 0.0], at + [0.0, 1.0]]), height, crs)[:, :2]
    map_to_enu = np.column_stack([enu[2] - enu[0], enu[3] - enu[0]])
    flip = np.diag([1.0, -1.0])  # rows run south: the curvature's y is north's opposite
    covariance = map_to_enu @ flip @ covariance_map @ flip @ map_to_enu.T + settings.floor_m**2 * np.eye(2)
    return OrthoRegistration(body[:2] + enu[1] - enu[0], covariance, peak, margin, pixels,
                             time.perf_counter() - started)


def _curvature(score: np.ndarray, x: int, y: int) -> np.ndarray:
    """Minus the Hessian (2x2, per pixel^2, x then y) of the correlation at its peak, from the
    3x3 around it."""
    s = score[y - 1:y + 2, x - 1:x + 2].astype(float)
    dxx = s[1, 2] - 2.0 * s[1, 1] + s[1, 0]
    dyy = s[2, 1] - 2.0 * s[1, 1] + s[0, 1]
    dxy = (s[2, 2] - s[2, 0] - s[0, 2] + s[0, 0]) / 4.0
    return -np.array([[dxx, dxy], [dxy, dyy]])


def peak_offset(score: np.ndarray, x: int, y: int) -> tuple[float, float]:
    """Sub-cell position of a correlation peak (a parabola through it and its neighbours)."""
    def vertex(lo, mid, hi):
        den = lo - 2.0 * mid + hi
        return 0.0 if den >= 0 else float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5))

    dx = vertex(score[y, x - 1], score[y, x], score[y, x + 1]) if 0 < x < score.shape[1] - 1 else 0.0
    dy = vertex(score[y - 1, x], score[y, x], score[y + 1, x]) if 0 < y < score.shape[0] - 1 else 0.0
    return dx, dy
