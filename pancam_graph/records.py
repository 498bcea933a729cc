"""Frozen records that cross module borders: what a traverse source hands the back-end.

The border between front-end and back-end is the stereo observation (track id,
u_left, u_right, v per stop): the back-end never needs an image. Ground truth
travels separately (`GroundTruth`) and is used only for evaluation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from .geometry.geodesy import LocalFrame
from .geometry.rig import Rig


@dataclass(frozen=True)
class StereoObservations:
    """Rectified stereo measurements of tracked features: `uvv` rows are (u_left, u_right, v) px."""

    track_ids: np.ndarray  # (N,) int64
    uvv: np.ndarray  # (N, 3) float

    def __post_init__(self) -> None:
        if self.uvv.shape != (len(self.track_ids), 3):
            raise ValueError(f"uvv must be ({len(self.track_ids)}, 3), got {self.uvv.shape}")

    def __len__(self) -> int:
        return len(self.track_ids)

    @staticmethod
    def empty() -> StereoObservations:
        return StereoObservations(np.zeros(0, dtype=np.int64), np.zeros((0, 3)))


@dataclass(frozen=True)
class PanoramaFrame:
    """One stereo frame of a site panorama at known mast angles (radians)."""

    pan_rad: float
    tilt_rad: float
    observations: StereoObservations


@dataclass(frozen=True)
class HrcFrame:
    """Projection measurements (u, v) px of the high-resolution camera at known mast angles."""

    pan_rad: float
    tilt_rad: float
    track_ids: np.ndarray  # (N,)
    uv: np.ndarray  # (N, 2)


@dataclass(frozen=True)
class GpsFix:
    """A WGS84 fix of the antenna; height is ellipsoidal. Sigmas are 1-sigma in metres."""

    time_s: float
    lat_deg: float
    lon_deg: float
    h_m: float
    sigma_horizontal_m: float
    sigma_vertical_m: float


@dataclass(frozen=True)
class OdometryTrack:
    """Wheel odometry as recorded: the body pose in the odometry frame at each message time.
    Only differences between poses are used, so the odometry frame's origin does not matter."""

    source: str  # file and topic, for messages
    times_s: np.ndarray  # (N,) increasing
    odom_T_body: np.ndarray  # (N, 4, 4)

    def __len__(self) -> int:
        return len(self.times_s)


@dataclass(frozen=True)
class DeadReckoning:
    """Wheel odometry + IMU increment from the previous stop: prev_T_curr (4x4) and its 6x6
    covariance ordered [rotation, translation] in the current body frame (GTSAM convention).
    The covariance is the step's own noise, independent from step to step; the wheel slip
    shared by every step is the traverse's `wheel_slip`."""

    prev_T_curr: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        # One memory layout whatever made them (gtsam hands out column-major matrices): numpy's
        # products sum in layout-dependent order, so a traverse read back from files would
        # otherwise differ from the simulated one in the last bits.
        object.__setattr__(self, "prev_T_curr", np.ascontiguousarray(self.prev_T_curr, dtype=float))
        object.__setattr__(self, "covariance", np.ascontiguousarray(self.covariance, dtype=float))


@dataclass(frozen=True)
class SlipPrior:
    """Wheel slip shared along the traverse: odometry distance = (1 + slip) x true distance, with
    slip ~ N(mean, sigma) once per traverse (terrain and load, not step-to-step noise)."""

    mean: float = 0.0
    sigma: float = 0.05


@dataclass(frozen=True)
class Stop:
    """Everything the rover recorded at one stop."""

    index: int
    time_s: float
    stereo: StereoObservations
    site_id: int | None = None
    panorama: tuple[PanoramaFrame, ...] = ()
    hrc: tuple[HrcFrame, ...] = ()
    dead_reckoning: DeadReckoning | None = None
    dwell_s: float = 0.0  # the rover stands still for this long after time_s, then drives on
    ground: GroundPatch | None = None  # a site's ground from its panorama's images (none at measurement level)

    @property
    def departure_s(self) -> float:
        return self.time_s + self.dwell_s

    @property
    def is_site(self) -> bool:
        return self.site_id is not None


@dataclass(frozen=True)
class Traverse:
    """A recorded (or simulated) traverse plus the sensor set-up the estimator may know."""

    name: str
    rig: Rig
    origin: LocalFrame
    stops: tuple[Stop, ...]
    traverse_tilt_rad: float  # mast tilt of the navigation stereo pairs (pan = 0)
    image_noise_px: float
    gps_lever_arm_m: np.ndarray  # antenna in the body frame
    start_world_T_body: np.ndarray  # 4x4, surveyed start pose
    start_sigmas: np.ndarray  # (6,) [rot rad x3, pos m x3]
    wheel_slip: SlipPrior = SlipPrior()
    # The navigation stereo pair's left camera in the body frame; None: on the mast at pan 0 and
    # the traverse tilt (PanCam). A body-fixed pair (a car, a rover's navigation cameras) gives it.
    body_T_nav_left: np.ndarray | None = None
    # Records of the kinds that are not part of every stop (kinds/base.py), by kind name: the
    # GPS fixes are measurements["gps"], in time order.
    measurements: dict[str, tuple] = field(default_factory=dict)

    def body_T_nav(self) -> gtsam.Pose3:
        """The navigation pair's left camera in the body frame."""
        if self.body_T_nav_left is not None:
            return gtsam.Pose3(self.body_T_nav_left)
        return self.rig.body_T_left(0.0, self.traverse_tilt_rad)

    def keeping(self, stop_fields: set[str]) -> Traverse:
        """The traverse with only these of its stops' image records (`stereo`, `panorama`, `hrc`,
        `ground`): what a worker process running some configurations on given motions reads."""
        empty = StereoObservations.empty()
        cleared = {"stereo": empty, "panorama": (), "hrc": (), "ground": None}
        cleared = {name: value for name, value in cleared.items() if name not in stop_fields}
        return replace(self, stops=tuple(replace(stop, **cleared) for stop in self.stops))

    @property
    def gps_fixes(self) -> tuple[GpsFix, ...]:
        """The GPS kind's records, which evaluation and the views also read as a reference."""
        return self.measurements.get("gps", ())


@dataclass(frozen=True)
class GroundTruth:
    """True poses and landmarks; only evaluation may look at these."""

    world_T_body: np.ndarray  # (N, 4, 4)
    landmarks: np.ndarray  # (M, 3)
    wheel_slip: float | None = None  # the traverse's true slip, when simulated
    # The terrain's true elevation (m, local up) at (N, 2) east-north points, when simulated.
    terrain: Callable[[np.ndarray], np.ndarray] | None = field(default=None, repr=False, compare=False)
    # The true values of kinds' own variables, when simulated: kind name -> variable -> value
    # (the orbital kind's map biases).
    kinds: dict[str, dict[str, float]] = field(default_factory=dict)
    # Per site stop, the mast's true (pan, tilt) of each panorama frame and then each HRC frame,
    # when simulated off its readings ([errors] pan_tilt_resolution_deg): what a render takes.
    mast_angles: dict[int, tuple[tuple[float, float], ...]] = field(default_factory=dict, repr=False)

    @property
    def positions(self) -> np.ndarray:
        return self.world_T_body[:, :3, 3]


@dataclass(frozen=True)
class Trajectory:
    """Positions in a local metric frame, with full poses and times when the file has them."""

    source: str
    positions: np.ndarray  # (N, 3)
    times_s: np.ndarray | None = None  # (N,)
    world_T_body: np.ndarray | None = None  # (N, 4, 4)
    geodetic: np.ndarray | None = None  # (N, 3) lat, lon, h when read from a GPS log

    def __len__(self) -> int:
        return len(self.positions)

    def subset(self, index: np.ndarray) -> Trajectory:
        pick = lambda a: None if a is None else a[index]  # noqa: E731
        return Trajectory(self.source, self.positions[index], pick(self.times_s), pick(self.world_T_body),
                          pick(self.geodetic))


@dataclass(frozen=True)
class MapRaster:
    """A north-up raster of a site's map (an orbital DTM or orthoimage) in a projected CRS: pixel
    (row, col) covers map x from x0 + col * post to x0 + (col + 1) * post and y from
    y0 - (row + 1) * post to y0 - row * post (x east, y north, metres)."""

    values: np.ndarray  # (H, W): heights above the body's surface in m (NaN: no data), or grey levels
    x0_m: float  # the upper-left corner's map coordinates
    y0_m: float
    post_m: float
    crs_wkt: str

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Map x (W,) and y (H,) of the pixel centres."""
        rows, cols = self.values.shape
        return (self.x0_m + (np.arange(cols) + 0.5) * self.post_m,
                self.y0_m - (np.arange(rows) + 0.5) * self.post_m)

    def at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear interpolation at map points (N, 2); NaN outside the raster or next to no data."""
        from scipy.interpolate import RegularGridInterpolator

        x, y = self.centres()
        grid = RegularGridInterpolator((y[::-1], x), self.values[::-1].astype(float), bounds_error=False,
                                       fill_value=np.nan)
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        return grid(np.column_stack([xy[:, 1], xy[:, 0]]))


@dataclass(frozen=True)
class GroundPatch:
    """A site's ground seen from above, from its panorama's dense stereo: per cell of a
    horizontal grid of the body frame, the mean body-frame position of the ground pixels in it
    and their mean grey level (what the orbital kind correlates with an orthoimage)."""

    points_body: np.ndarray  # (N, 3) float32, m
    grey: np.ndarray  # (N,) float32, 0-255
    samples: np.ndarray  # (N,) int32: pixels averaged in each cell
    cell_m: float


@dataclass(frozen=True)
class OrbitalMap:
    """An orbital map of the traverse's ground: a DTM (heights above the body's surface) and,
    optionally, an orthoimage, with the accuracy its producer states for its georeference."""

    name: str
    dtm: MapRaster
    orthoimage: MapRaster | None = None
    offset_sigma_m: float = 3.0  # 1 sigma of its horizontal position, per axis
    rotation_sigma_deg: float = 0.02  # 1 sigma of its rotation about the traverse's origin
    vertical_sigma_m: float = 1.0  # 1 sigma of its heights' offset (its vertical datum)
    source: str = ""  # the DTM's file when it was read from one (messages name it)

    @property
    def called(self) -> str:
        """How messages name it: its DTM's file, else its name."""
        return f"{self.source} (orbital map {self.name!r})" if self.source else f"orbital map {self.name!r}"
