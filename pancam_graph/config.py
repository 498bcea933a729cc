"""Scenario configuration: pydantic models (extra keys forbidden) loaded from TOML.

Lengths in metres, angles in degrees at this user-facing layer (converted to radians
where they enter the code), path distances measured along the path from its start.
"""

from __future__ import annotations

import math
import re
import textwrap
import tomllib
import typing
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, TypeVar

import tomli_w
from pydantic import AfterValidator, BaseModel, Field, ValidationError, create_model, field_validator, model_validator

from .errors import ConfigError, PancamGraphError
from .kinds import KINDS, configuration_problem
from .kinds.base import Section
from .runtime.text_files import read_text

# -- the options only some sources take (each source says which: sources/): their names,
# command-line flags, help and checks, written once. The CLI's flags, its --resume clash check and
# a run's reproduce.sh all come from here.

DETECTORS = ("gftt", "orb", "sift")
ERROR_PROFILES = ("ideal", "realistic")


def check_error_profile(name: str | None) -> None:
    """`--errors NAME`: a profile [errors] knows (None: not given)."""
    if name is not None and name not in ERROR_PROFILES:
        raise ConfigError(f"--errors {name!r}: expected {' or '.join(ERROR_PROFILES)}")


def _option(flag: str, help: str, minimum: float | None = None):
    return field(default=None, metadata={"flag": flag, "help": help, "minimum": minimum})


@dataclass(frozen=True)
class SourceOptions:
    """None: not given. One given to a source that does not take it is an error (`check`)."""

    seed: int | None = _option("--seed", "scenario: override its seed", minimum=0)
    errors: str | None = _option("--errors", "scenario: the simulator's error profile, ideal or realistic, in "
                                 "place of its [errors] table (docs/simulation_errors.md)")
    gps_topic: str | None = _option("--gps-topic", "bag: NavSatFix topic (default: the only one)")
    odom_topic: str | None = _option("--odom-topic", "bag: Odometry topic (default: the only one)")
    holdout_every: int | None = _option("--holdout-every", "bag, KITTI: keep every N-th fix out of the graph "
                                        "for scoring (default 5; 0: use all)", minimum=0)
    geoid_height_m: float | None = _option("--geoid-height", "KITTI: geoid height (m) added to OXTS alt")
    detector: str | None = _option("--detector", "image sources: gftt (default), orb or sift")
    skip_bad_frames: bool | None = _option("--skip-bad-frames", "image sources: a missing, truncated or "
                                           "wrong-sized image leaves its stop to the VO bridge (default: stop "
                                           "with a message naming the file)")
    # as text on the command line: LEFT,RIGHT
    stereo_topics: tuple[str, str] | None = _option("--stereo-topics", "bag: LEFT,RIGHT rectified image topics "
                                                    "for stereo VO (CameraInfo beside each: .../camera_info)")

    def __post_init__(self) -> None:
        flags = self.flags()
        for f in fields(self):
            value, minimum = getattr(self, f.name), f.metadata["minimum"]
            if minimum is not None and value is not None and value < minimum:
                raise ConfigError(f"{flags[f.name]} {value}: must be at least {minimum}")
        check_error_profile(self.errors)
        if self.detector is not None and self.detector not in DETECTORS:
            raise ConfigError(f"--detector {self.detector!r}: expected {', '.join(DETECTORS[:-1])} or {DETECTORS[-1]}")
        if isinstance(self.stereo_topics, str):
            topics = tuple(t.strip() for t in self.stereo_topics.split(",") if t.strip())
            if len(topics) != 2:
                raise ConfigError(f"--stereo-topics {self.stereo_topics!r}: expected LEFT,RIGHT (two image topics)")
            object.__setattr__(self, "stereo_topics", topics)

    @staticmethod
    def flags() -> dict[str, str]:
        """Option name -> its command-line flag."""
        return {f.name: f.metadata["flag"] for f in fields(SourceOptions)}

    @staticmethod
    def help(name: str) -> str:
        return SourceOptions._metadata(name)["help"]

    @staticmethod
    def minimum(name: str) -> float | None:
        return SourceOptions._metadata(name)["minimum"]

    @staticmethod
    def _metadata(name: str):
        return next(f.metadata for f in fields(SourceOptions) if f.name == name)

    def given(self) -> dict[str, object]:
        """The options set (not None), by name."""
        return {name: getattr(self, name) for name in self.flags() if getattr(self, name) is not None}

    def check(self, kind: str, allowed: set[str] | frozenset[str]) -> None:
        for name in self.given():
            if name not in allowed:
                raise ConfigError(f"{self.flags()[name]} does not apply to a {kind} source")


def _ordered(pair: tuple[float, float]) -> tuple[float, float]:
    if pair[0] > pair[1]:
        raise ValueError("must be (min, max) with min <= max")
    return pair


# A (min, max) pair; every float of every model is finite (allow_inf_nan=False below).
Range = Annotated[tuple[float, float], AfterValidator(_ordered)]
# A coordinate or offset in metres: beyond 1000 km it is a typo, and would allocate terrain
Metres = Annotated[float, Field(ge=-1e6, le=1e6)]
Degrees = Annotated[float, Field(ge=-90.0, le=90.0)]
M = TypeVar("M", bound=BaseModel)


_Strict = Section


class OriginConfig(_Strict):
    """Geodetic origin of the local ENU frame: on Earth WGS84 with ellipsoidal height, on Mars the
    IAU 2015 sphere (planetocentric latitude, east longitude, height above the sphere)."""

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    h_m: float = Field(0.0, ge=-10000.0, le=22000.0, description="height above the body's reference surface "
                       "(Earth: ellipsoidal; Mars reaches -8 km in Hellas and 22 km on Olympus Mons)")
    body: Literal["earth", "mars"] = "earth"


class Serpentine(_Strict):
    """A survey serpentine: `legs` straight legs of `leg_m` east and west in turn, each `spacing_m`
    north of the last, joined by sharp turns; each leg bends `wiggle_m` aside at its thirds, and
    every waypoint's elevation is drawn within +-`relief_m` (numpy's generator `relief_seed`)."""

    legs: int = Field(ge=1, le=1000)
    leg_m: float = Field(gt=0.0, le=100000.0)
    spacing_m: float = Field(gt=0.0, le=10000.0)
    wiggle_m: float = Field(0.0, ge=0.0, le=1000.0)
    relief_m: float = Field(0.0, ge=0.0, le=1000.0)
    relief_seed: int = Field(0, ge=0)

    def waypoints(self) -> tuple[list[tuple[float, float, float]], list[int]]:
        """(waypoints east, north, elevation; the indices of the sharp turns)."""
        import numpy as np

        heights = np.random.default_rng(self.relief_seed).uniform(-self.relief_m, self.relief_m, 4 * self.legs)
        points: list[tuple[float, float, float]] = []
        for leg in range(self.legs):
            north = leg * self.spacing_m
            for i, third in enumerate((0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)):
                along = third if leg % 2 == 0 else 1.0 - third
                aside = 0.0 if i in (0, 3) else self.wiggle_m * (1.0 if (2 * leg + i) % 2 else -1.0)
                points.append((round(along * self.leg_m, 3), round(north + aside, 3),
                               round(float(heights[len(points)]), 3)))
        turns = [i for leg in range(self.legs) for i in (4 * leg, 4 * leg + 3) if 0 < i < 4 * self.legs - 1]
        return points, turns


# A traverse's size limit (six mission_traverses), and what the refusal predicts from measured
# costs a stop (docs/performance.md, "Figures behind the code")
MAX_STOPS = 200_000
SECONDS_PER_STOP = 0.0097
SIMULATION_BYTES_PER_STOP = 27_000


class PathConfig(_Strict):
    """The driven path: waypoints (east m, north m, elevation m relative to the origin), written
    out or generated by a `serpentine`."""

    waypoints: list[tuple[Metres, Metres, Metres]] = Field(default_factory=list, max_length=100000)
    serpentine: Serpentine | None = Field(None, description="generate the waypoints and sharp turns instead of "
                                          "writing them out")
    sharp_turns: list[int] = Field(default_factory=list, description="waypoint indices kept as corners")
    stop_spacing_m: Range = (1.0, 2.0)
    speed_mps: float = Field(0.1, gt=0.0, le=10.0)
    dwell_s: float = Field(20.0, ge=0.0, le=86400.0)

    @model_validator(mode="before")
    @classmethod
    def _generate(cls, data):
        """A serpentine's waypoints, unless they are written out too (a run's run.toml)."""
        if isinstance(data, dict) and isinstance(data.get("serpentine"), dict) and "waypoints" not in data:
            try:
                waypoints, turns = Serpentine.model_validate(data["serpentine"]).waypoints()
            except ValidationError:
                return data  # reported at the serpentine's own fields
            return {**data, "waypoints": waypoints, "sharp_turns": turns}
        return data

    @property
    def length_m(self) -> float:
        """The waypoints' polyline length."""
        return sum(math.dist(a, b) for a, b in zip(self.waypoints, self.waypoints[1:], strict=False))

    @model_validator(mode="after")
    def _check(self) -> PathConfig:
        if len(self.waypoints) < 2:
            raise ValueError("give at least 2 waypoints, or a serpentine")
        if self.serpentine is not None:
            waypoints, turns = self.serpentine.waypoints()
            if [tuple(w) for w in self.waypoints] != waypoints or self.sharp_turns != turns:
                raise ValueError("give the waypoints and sharp_turns or a serpentine, not both")
        lo, hi = self.stop_spacing_m
        if not 0.05 <= lo <= hi <= 100.0:
            raise ValueError("stop_spacing_m must be (min, max) with 0.05 <= min <= max <= 100 m")
        for i in self.sharp_turns:
            if not 0 < i < len(self.waypoints) - 1:
                raise ValueError(f"sharp_turns index {i} is not an interior waypoint")
        steps = [math.dist(a, b) for a, b in zip(self.waypoints, self.waypoints[1:], strict=False)]
        if 0.0 in steps:
            i = steps.index(0.0)
            raise ValueError(f"waypoints {i} and {i + 1} are the same point: a path needs distinct consecutive "
                             "waypoints")
        length = sum(steps)
        if length < hi:
            raise ValueError(f"the path is {length:.2f} m long, shorter than one stop spacing ({hi} m)")
        stops = length / ((lo + hi) / 2.0)
        if stops > MAX_STOPS:
            hours = stops * SECONDS_PER_STOP / 3600.0
            raise ValueError(
                f"the path is {length / 1000:,.0f} km at {lo:g}-{hi:g} m a stop: about {stops:,.0f} stops, more than "
                f"the {MAX_STOPS:,} a run takes (predicted at least {hours:,.1f} h on 2 cores and a simulation that "
                f"grows past {stops * SIMULATION_BYTES_PER_STOP / 1e9:,.0f} GB, from mission_traverse's measured "
                "cost); split the traverse, or space its stops wider")
        return self


class TerrainConfig(_Strict):
    landmark_density_per_m2: float = Field(0.5, gt=0.0, le=20.0)
    corridor_half_width_m: float = Field(45.0, gt=0.0, le=1000.0)
    undulation_m: float = Field(0.8, ge=0.0, le=100.0)
    roughness_m: float = Field(0.2, ge=0.0, le=10.0)
    featureless: list[Range] = Field(default_factory=list, description="path-distance ranges, m")
    featureless_density_factor: float = Field(0.01, ge=0.0, le=1.0)
    craters_per_km2: float = Field(0.0, ge=0.0, le=20000.0, description="small impact craters (bowl and rim), "
                                   "the relief an orbital DTM at 1 m posts resolves and a site's map registers on")
    crater_radius_m: Range = Field((2.0, 15.0), description="crater radii, drawn from a -2 power law between these")

    @field_validator("crater_radius_m")
    @classmethod
    def _positive_radii(cls, radii: tuple[float, float]) -> tuple[float, float]:
        if radii[0] <= 0:
            raise ValueError(f"crater radii must be positive, got {radii[0]:g} m")
        return radii


class CameraConfig(_Strict):
    image_noise_px: float = Field(0.3, gt=0.0, le=50.0)
    outlier_fraction: float = Field(0.05, ge=0.0, lt=0.5)
    traverse_tilt_deg: float = Field(-12.0, ge=-90.0, le=90.0)
    vo_range_m: Range = (2.0, 25.0)


class SitesConfig(_Strict):
    enabled: bool = True
    spacing_m: Range = (30.0, 60.0)
    pan_range_deg: Range = Field((-180.0, 180.0), description="full panorama: (-180, 180)")
    pan_step_deg: float = Field(30.0, ge=1.0, le=360.0)
    tilts_deg: list[Degrees] = Field(default_factory=lambda: [-6.0, -22.0], max_length=20)
    max_range_m: float = Field(40.0, gt=0.0, le=10000.0)
    hrc: bool = True
    hrc_tilt_deg: Degrees = -5.0
    hrc_pan_step_deg: float | None = Field(None, ge=1.0, le=360.0, description="HRC frames every this many "
                                           "degrees of pan over pan_range_deg (default: pan_step_deg, one "
                                           "HRC frame per panorama column)")
    dwell_s: float = Field(900.0, ge=0.0, le=86400.0, description="time a site's panorama takes (the rover "
                           "stands still)")

    @model_validator(mode="after")
    def _check(self) -> SitesConfig:
        if self.spacing_m[0] <= 0.0:
            raise ValueError(f"spacing_m must be positive, got {list(self.spacing_m)}")
        if self.enabled and not self.tilts_deg:
            raise ValueError("tilts_deg is empty: a site panorama needs at least one tilt (enabled = false turns "
                             "sites off)")
        lo, hi = self.pan_range_deg
        if not -360.0 <= lo <= hi <= 360.0:
            raise ValueError(f"pan_range_deg must lie within (-360, 360), got {list(self.pan_range_deg)}")
        frames = (int((hi - lo) / self.pan_step_deg) + 1) * max(len(self.tilts_deg), 1)
        if self.hrc:
            frames += int((hi - lo) / (self.hrc_pan_step_deg or self.pan_step_deg)) + 1
        if frames > 2000:
            raise ValueError(f"pan_range_deg, pan_step_deg, tilts_deg and hrc_pan_step_deg give {frames} frames "
                             "per site (at most 2000)")
        return self


class GpsConfig(_Strict):
    enabled: bool = True
    sigma_horizontal_m: float = Field(2.0, gt=0.0, le=1000.0)
    sigma_vertical_m: float = Field(3.0, gt=0.0, le=1000.0)
    every_n_stops: int = Field(1, ge=1, le=1000, description="fixes at stops (ignored when rate_hz is set); "
                               "beyond 1000 stops (kilometres) a traverse has no GPS to speak of: enabled = false")
    rate_hz: float | None = Field(None, gt=0.0, le=20.0,
                                  description="fixes at this rate over the whole drive, between stops too")
    dropouts: list[Range] = Field(default_factory=list, description="path-distance ranges, m")
    multipath_fraction: float = Field(0.0, ge=0.0, lt=1.0)
    multipath_offset_m: Range = (15.0, 60.0)
    lever_arm_m: tuple[float, float, float] = Field((0.0, 0.0, 1.8), description="antenna in the body frame")

    @model_validator(mode="after")
    def _check(self) -> GpsConfig:
        if max(abs(v) for v in self.lever_arm_m) > 10.0:
            raise ValueError(f"lever_arm_m must be within 10 m of the body origin, got {list(self.lever_arm_m)}")
        return self


class DeadReckoningConfig(_Strict):
    """Wheel odometry (distance with slip) and an IMU (heading with drift, absolute tilt)."""

    enabled: bool = True
    wheel_slip_mean: float = Field(0.03, ge=-0.5, le=1.0, description="expected slip: odometry distance / true "
                                   "distance - 1")
    wheel_slip_bias_sigma: float = Field(0.02, ge=0.0, le=1.0, description="the traverse's slip differs from the mean "
                                         "by this much (1 sigma), the same at every step")
    wheel_slip_sigma: float = Field(0.03, ge=0.0, le=1.0, description="step-to-step slip noise around the "
                                    "traverse's")
    heading_noise_deg: float = Field(0.2, ge=0.0, le=90.0)
    gyro_drift_deg_per_h: float = Field(2.0, ge=0.0, le=3600.0)
    tilt_noise_deg: float = Field(0.1, ge=0.0, le=90.0)


# Each configuration is a named list of measurement kinds (pancam_graph/kinds/). A run solves
# every configuration whose kinds the traverse can feed, unless `run --configs` picks some.
DEFAULT_CONFIGURATIONS: dict[str, list[str]] = {
    "dead_reckoning": ["dead_reckoning", "wheel_slip"],  # the baseline VO is meant to beat
    # With wheel_slip: GPS makes the shared slip observable, and without it the run claims a third
    # of the variance it has at its end (docs/results.md, "The last stop's NEES over the seeds").
    "dead_reckoning_gps": ["dead_reckoning", "gps", "wheel_slip"],
    "vo": ["vo"],
    "vo_sites": ["vo", "sites"],
    "vo_sites_hrc": ["vo", "sites", "hrc"],
    "full": ["vo", "sites", "hrc", "gps"],
    # Mars has no GPS: the orbital map (and the sun) are its absolute references
    "vo_sites_orbital": ["vo", "sites", "orbital"],
    "full_mars": ["vo", "sites", "hrc", "orbital", "sun_heading"],
}


# The VO error models an estimator can name (`vo_error_model`) and the values each sets
# (docs/frontend.md, "The VO error model on real images"). pixel_noise sets nothing: the two-stop
# adjustment's covariance from white pixel noise alone, the truth in simulation. real_images is
# what real pixel errors need besides, measured on real KITTI frames: features within 40 m,
# per-step floors of 0.5 % of the step and 0.03 deg/m (the RMS of what white noise leaves), and
# a scale and a direction bias shared by every step (the vo_scale kind, added to every
# configuration with vo; a dict sets keys of a kind's section).
VO_ERROR_MODELS: dict[str, dict] = {
    "pixel_noise": {},
    "real_images": {"vo_max_range_m": 40.0, "vo_translation_floor": 0.005,
                    "vo_rotation_floor_deg_per_m": 0.03, "vo_scale": {"direction_sigma": 0.005}},
}
SHARED_SCALE_MODELS = ("real_images",)  # the models that add vo_scale to configurations with vo

# What tracking errors (the image front-end's, as sim/errors.TrackingErrors draws them) do to
# the VO: its steps' errors are correlated from step to step (a feature's disparity error and
# drift go on along its track), which a step's own covariance cannot say, and the graph takes
# the steps as independent. Over chains of 30 steps (about a site spacing) of the realistic
# measurement level, the error is 1.68-1.91, 1.53-1.93 and 1.62-1.67 times the chain's claimed
# sigma in heading, forward and lateral (short_trail seeds 0-9 and denver_trail seeds 0-3, 266
# chains; a single step's 1.37-1.48), and below it in roll, pitch and height (0.55-0.92, left
# at 1). A step's sigmas in the body's (roll, pitch, yaw, x, y, z) are multiplied by these where
# the scenario's [errors] draws those errors (vo_sigma_scale). The rendered images' own VO errs
# by 1.3-1.5 times more again over 30 steps (2.55, 2.53, 2.29; docs/simulation_errors.md):
# what the drawn errors leave out.
TRACKED_VO_SIGMA_SCALE = (1.0, 1.0, 1.8, 1.8, 1.65, 1.0)


# Estimator keys that moved into their kind's own section, [estimator.<kind>] (kinds/<kind>.py).
MOVED_KEYS = {
    "gps_kernel": ("gps", "kernel"), "gps_outlier_probability": ("gps", "outlier_probability"),
    "gps_time_association": ("gps", "time_association"), "gps_max_gap_s": ("gps", "max_gap_s"),
    "tie_points_per_site": ("sites", "points_per_site"), "tie_sigma_px": ("sites", "sigma_px"),
    "site_memory": ("sites", "memory"), "landmark_anchor_sigma_m": ("sites", "anchor_sigma_m"),
    "tie_kernel": ("sites", "kernel"), "hrc_gate_px": ("hrc", "gate_px"), "hrc_sigma_px": ("hrc", "sigma_px"),
    "vo_scale_sigma": ("vo_scale", "sigma"),
}


_Scale = Annotated[float, Field(gt=0.0, le=100.0)]


class _EstimatorCore(_Strict):
    """Every constant of the estimator: what is written with the results is the whole story.
    A measurement kind with its own constants (`Kind.Settings`) adds them as a section named
    after it, `[estimator.<kind>]` (EstimatorConfig below)."""

    vo_min_inliers: int = Field(12, ge=6)
    vo_ransac_px: float = Field(1.5, gt=0.0)
    vo_max_step_m: float = Field(5.0, gt=0.0)
    vo_pnp_iterations: int = Field(1000, ge=10, description="RANSAC iterations (at most) of the PnP initial "
                                   "pose: 200 left bad steps where few tracks survive (rendered denver_trail)")
    vo_pnp_confidence: float = Field(0.999, gt=0.0, lt=1.0)
    vo_max_range_m: float = Field(40.0, gt=0.0, description="VO uses features nearer than this: a far "
                                  "feature's range error (grows with range squared) biases the scale")
    vo_error_model: Literal[tuple(VO_ERROR_MODELS)] = Field(
        "pixel_noise", description="pixel_noise: white pixel noise alone (simulation); real_images: the model "
        "measured on real images, which sets vo_max_range_m and the two floors below and adds vo_scale to every "
        "configuration with vo (config.VO_ERROR_MODELS)")
    vo_translation_floor: float = Field(0.0, ge=0.0, lt=1.0, description="per-step translation error the pixel "
                                        "noise does not explain, as a fraction of the step (real images)")
    vo_rotation_floor_deg_per_m: float = Field(0.0, ge=0.0, lt=10.0, description="the same for rotation")
    vo_sigma_scale: tuple[_Scale, _Scale, _Scale, _Scale, _Scale, _Scale] | None = Field(
        None, description="each VO step's sigmas in the body's (roll, pitch, yaw, x, y, z) times these: what "
        "tracking errors correlated from step to step add over a chain of steps, which a step's own covariance "
        "cannot say (config.TRACKED_VO_SIGMA_SCALE where the scenario's [errors] stereo_tracking is measured); "
        "None: 1")
    huber_k: float = Field(1.345, gt=0.0, description="Huber threshold in sigmas of one dimension (95 % "
                           "efficiency); a factor of d dimensions gets the norm threshold its inliers pass as often "
                           "(graph/noise.norm_threshold: 1.86 for 2, 2.22 for 3)")
    cauchy_k: float = Field(1.0, gt=0.0, description="Cauchy threshold, the same way")
    start_sigma_deg: float = Field(0.05, gt=0.0)
    start_sigma_m: float = Field(0.02, gt=0.0)
    relinearize_rotation_rad: float = Field(0.02, gt=0.0, description="iSAM2 relinearizes a pose whose "
                                            "rotation moved this far from its linearization point")
    relinearize_translation_m: float = Field(0.1, gt=0.0, description="... or whose position, or a landmark "
                                             "whose position, moved this far (GPS moves whole stretches of "
                                             "poses by centimetres: a 5 cm threshold relinearized hundreds a stop; "
                                             "a tie's robust weight is taken where its pose and landmark were "
                                             "linearized unless [estimator.sites] weights = \"estimate\")")
    relinearize_scalar: float = Field(0.05, gt=0.0, description="... or a scalar (wheel slip, VO scale) this far")
    relinearize_calibration: float = Field(2e-5, gt=0.0, description="... or a term of the stereo pair's "
                                           "calibration error this far (a tenth of its prior's rotation sigma): "
                                           "its factors' robust weights are taken at its linearization point")
    relinearize_check: Literal["auto", "full", "partial"] = Field(
        "auto", description="which variables iSAM2 checks against the thresholds: full, every one; partial, "
        "from the newest down only while a clique has one past them (GTSAM's partial check). auto is partial for "
        "configurations with GPS (see relinearize_skip), full for the others")
    relinearize_skip: Literal["auto"] | Annotated[int, Field(ge=1)] = Field(
        "auto", description="iSAM2 checks the thresholds at every this many updates. auto is 10 (GTSAM's default) "
        "with the partial check for configurations with GPS: a fix moves old poses and landmarks just past the "
        "thresholds, and relinearizing one re-eliminates everything from it up to the newest (docs/performance.md); "
        "1 for the others")
    factorization: Literal["auto", "qr", "cholesky"] = Field(
        "auto", description="iSAM2's: auto is Cholesky for configurations with GPS (a third faster; GPS bounds the "
        "uncertainty) and QR for the others (Cholesky fails on long VO chains); a Cholesky that fails goes on as QR")
    wildfire_threshold: float = Field(0.01, gt=0.0, description="iSAM2's back-substitution after an update stops "
                                      "where the change falls below this (rad or m; GTSAM's default 0.001 made the "
                                      "GPS fixes' updates reach the whole trajectory); the final estimate is "
                                      "back-substituted in full")
    window_m: float = Field(1000.0, gt=0.0, description="iSAM2 smooths over this many metres of travel: a "
                            "variable is marginalized once the rover has driven this far past the stop where "
                            "it entered (bounded cost per stop on long traverses); inf: the whole traverse")
    configurations: dict[str, list[str]] = Field(default_factory=lambda: dict(DEFAULT_CONFIGURATIONS),
                                                 description="name -> measurement kinds (pancam_graph/kinds/)")
    calibration: Literal["auto", "trusted", "estimated"] = Field(
        "auto", description="the stereo pair's calibration: trusted as given, or estimated (every configuration "
        "with vo or sites gets stereo_calibration, in place of vo_scale); auto: estimated where a scenario's [errors] "
        "profile is realistic, trusted elsewhere")

    @model_validator(mode="before")
    @classmethod
    def _vo_error_model(cls, data):
        """A named VO error model sets its values (a file that sets them too is overruled: its
        own values go with vo_error_model = "pixel_noise")."""
        # a list or table given for the name is left to the field's own check, which names it
        if isinstance(data, dict) and isinstance(data.get("vo_error_model"), str) and \
                data["vo_error_model"] in VO_ERROR_MODELS:
            data = dict(data)
            for key, value in VO_ERROR_MODELS[data["vo_error_model"]].items():
                section = data.get(key)
                if isinstance(value, dict) and isinstance(section, BaseModel):
                    section = section.model_dump(exclude_unset=True)
                data[key] = {**section, **value} if isinstance(value, dict) and isinstance(section, dict) else value
            if data["vo_error_model"] in SHARED_SCALE_MODELS:
                configurations = data.get("configurations", DEFAULT_CONFIGURATIONS)
                if isinstance(configurations, dict):  # else the field's own check names it
                    data["configurations"] = {name: _with_shared_scale(kinds)
                                              for name, kinds in configurations.items()}
        return data

    @model_validator(mode="before")
    @classmethod
    def _estimated_calibration(cls, data):
        """An estimated calibration adds its kinds to the configurations that can take them."""
        if isinstance(data, dict) and data.get("calibration") == "estimated":
            configurations = data.get("configurations", DEFAULT_CONFIGURATIONS)
            if isinstance(configurations, dict):  # else the field's own check names it
                data = {**data, "configurations": {name: _with_calibration(kinds)
                                                   for name, kinds in configurations.items()}}
        return data

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data):
        """Keys that became a kind's own section say where they went."""
        if isinstance(data, dict):
            for old, (section, new) in MOVED_KEYS.items():
                if old in data:
                    raise ValueError(f"{old} moved to the section [estimator.{section}] as {new}")
        return data

    def kernel_k(self, kernel: str) -> float | None:
        """The threshold (sigmas) of a robust kernel named in this configuration."""
        return {"huber": self.huber_k, "cauchy": self.cauchy_k}.get(kernel)

    @model_validator(mode="after")
    def _check_configurations(self) -> _EstimatorCore:
        for name, kinds in self.configurations.items():
            problem = configuration_problem(kinds)
            if problem:
                raise ValueError(f"configuration {name!r}: {problem}")
        return self


def _kind_sections(attribute: str) -> dict:
    """One field per kind that defines the section model `attribute`, named after the kind."""
    return {name: (getattr(kind, attribute), getattr(kind, attribute)())
            for name, kind in KINDS.items() if getattr(kind, attribute) is not None}


EstimatorConfig = create_model("EstimatorConfig", __base__=_EstimatorCore, __module__=__name__,
                               **_kind_sections("Settings"))


class FrontendConfig(_Strict):
    """Images -> stereo observations (frontend/tracker.py). Pixels unless said otherwise."""

    detector: Literal[DETECTORS] = "gftt"
    max_features: int = Field(1500, ge=20, le=20000, description="features kept per frame")
    min_distance_px: int = Field(8, ge=1, le=100, description="between corners")
    gftt_quality: float = Field(0.001, gt=0.0, lt=1.0, description="of a cell's strongest corner")
    detection_grid: int = Field(1, ge=1, le=16, description="corners are found in grid x grid cells, and new ones "
                                "go first to the cells with the fewest tracks")
    klt_window_px: int = Field(11, ge=5, le=101, description="11 px: more accurate and 2x faster than 21 "
                               "on the real KITTI frames (docs/frontend.md)")
    klt_levels: int = Field(3, ge=0, le=6)
    mutual_max_px: float = Field(0.5, gt=0.0, description="forward-backward (and left-right-left) distance")
    row_max_px: float = Field(1.0, gt=0.0, description="a stereo match's row difference (rectified)")
    min_disparity_px: float = Field(0.5, ge=0.0)
    max_disparity_px: float = Field(250.0, gt=0.0)
    initial_disparity_px: float = Field(10.0, ge=0.0, description="where optical flow starts for a new feature")
    smoothness_px: float = Field(3.0, gt=0.0, description="Delaunay disparity smoothness, absolute")
    smoothness_fraction: float = Field(0.25, gt=0.0, description="... and relative to the neighbour's")
    ratio: float = Field(0.8, gt=0.0, le=1.0, description="descriptor detectors: Lowe's ratio test")
    max_motion_px: float = Field(150.0, gt=0.0, description="descriptor detectors: image motion between frames")
    odometry_aided: bool = Field(True, description="image folders with dead reckoning: search each track where "
                                 "the odometry says it went (MER's VO does the same)")
    ground_warp: bool = Field(True, description="with the motion known: track features on the ground from the "
                              "previous image warped by the ground's homography (no perspective bias: "
                              "docs/frontend.md)")
    ground_warp_range_m: float = Field(25.0, gt=0.0, description="ground plane fitted to features nearer than this")
    ground_warp_tolerance_m: float = Field(0.15, gt=0.0, description="a feature this near the plane is on it")
    prediction_gate_px: float = Field(
        20.0, gt=0.0, description="with the motion since the last frame known (wheel odometry): a track whose "
        "offset from its predicted position differs from the median offset by more is dropped")


class RenderConfig(_Strict):
    """How `pancam-graph render` images a scenario: a real lens, a real misaligned stereo pair,
    rocks, and the site panoramas. The defaults are the ExoMars PanCam emulator's measured radial
    distortion (ESA Katwijk data set, shared/data/real/katwijk_pancam_calib)."""

    distortion: tuple[float, float, float, float] = Field(
        (-0.2645, 0.2626, 0.0, 0.0), description="k1, k2, p1, p2 of both WACs (OpenCV order); zeros: a pinhole")
    right_rotation_deg: tuple[float, float, float] = Field(
        (0.05, -0.08, 0.06), description="the right WAC's misalignment about its x, y, z axes")
    right_focal_scale: float = Field(1.002, gt=0.9, lt=1.1, description="right WAC focal length / left's")
    right_principal_offset_px: tuple[float, float] = (2.5, -1.5)
    sensor_noise_dn: float = Field(1.5, ge=0.0, le=50.0, description="read noise, 8-bit DN (1 sigma)")
    rocks_per_100m2: float = Field(2.0, ge=0.0, le=50.0, description="rocks 0.15-1 m across, off the path")
    panoramas: bool = Field(True, description="render the site panoramas (WAC pairs and HRC frames)")


# The realistic profile's magnitudes (docs/simulation_errors.md): each with the measurement or
# specification it comes from. Never set to reach a drift figure: the drift is the result.
REALISTIC_ERRORS: dict[str, tuple[object, str]] = {
    "focal_scale_sigma": (0.0003, "the project's calibration of the rendered control field (`calibrate`, 4 views): "
                                  "fx 1 sigma 0.54 px of 1724 px, error +0.022 / +0.024 %"),
    "focal_difference_sigma": (0.00005, "the same calibration: the two cameras' focal errors differ by 0.002 % "
                                        "(4 views) and 0.007 % (6 views)"),
    "baseline_scale_sigma": (0.0001, "the same calibration: baseline +0.000 mm (4 views) and +0.034 mm (6 views) of "
                                     "500 mm; 0.01 % taken"),
    "boresight_sigma_deg": (0.01, "the same calibration: the right camera's rotation off by 0.0165 deg (4 views), "
                                  "about 0.01 deg per axis"),
    "pan_tilt_resolution_deg": (0.013, "the dissertation's pan/tilt unit resolves 0.013 deg (its stereo matching aided "
                                       "by the rotary platform's angles): a reading is off by up to half of it"),
    "stereo_tracking": ("measured", "the image front-end's navigation features against the renderer's depth on "
                                    "rendered short_trail seeds 0 and 5 and denver_trail seed 1 (120 stops each): "
                                    "disparity error 0.57-0.59 px, 0.70-0.73 correlated from stop to stop along a "
                                    "track; the left pixel's error grows along the track, 0.31-0.34 px (column) and "
                                    "0.11 px (row) after a stop, 1.69-1.74 and 0.42-0.44 px after eight; 0.73-0.76 "
                                    "of a stop's features tracked on (scripts/vo_tracking_truth.py)"),
    "tie_matching": ("measured", "the image front-end's tie points against the renderer's truth on denver_trail "
                                 "seeds 0 and 1 (49 site pairs): 130 ties at 31 m, 33 at 49 m, none from 60 m; "
                                 "median error 0.37-1.1 px, 3.0 % beyond 3 px (sim/errors.py)"),
}


class SimulationErrors(_Strict):
    """[errors]: what the simulated rover gets wrong that its estimator does not know. `ideal`
    (the default) leaves them all out, as the simulator always has; `realistic` takes each
    magnitude from REALISTIC_ERRORS (a key given in the scenario overrides it)."""

    profile: Literal["ideal", "realistic"] = "ideal"
    focal_scale_sigma: float = Field(0.0, ge=0.0, le=0.05, description="per run: the true focal lengths / the "
                                     "calibrated ones - 1, common to both cameras (1 sigma)")
    focal_difference_sigma: float = Field(0.0, ge=0.0, le=0.05, description="per run: the right camera's focal "
                                          "error beyond the common one (1 sigma): a disparity error across the image")
    baseline_scale_sigma: float = Field(0.0, ge=0.0, le=0.05, description="per run: the true stereo baseline / the "
                                        "calibrated one - 1 (1 sigma)")
    boresight_sigma_deg: float = Field(0.0, ge=0.0, le=5.0, description="per run: the right camera's rotation after "
                                       "calibration, per axis (1 sigma): about its vertical it biases every disparity")
    pan_tilt_resolution_deg: float = Field(0.0, ge=0.0, le=5.0, description="per frame: the mast's pan and tilt "
                                           "readings are the true angles rounded to this")
    stereo_tracking: Literal["white", "measured"] = Field(
        "white", description="white: a navigation frame's pixels off by white noise (camera.image_noise_px); measured: "
        "as the image front-end tracks them, a disparity error kept along the track and a pixel drifting from stop "
        "to stop (sim/errors.TrackingErrors)")
    tie_matching: Literal["identity", "measured"] = Field(
        "identity", description="identity: every landmark two sites see is a tie at the pixel noise; measured: the "
        "image matcher's count against distance, accuracy and near-miss mismatches")

    @model_validator(mode="before")
    @classmethod
    def _profile(cls, data):
        if isinstance(data, dict) and data.get("profile") == "realistic":
            return {**{key: value for key, (value, _) in REALISTIC_ERRORS.items()}, **data}
        return data

    @property
    def calibration(self) -> bool:
        """Whether the stereo pair's calibration is off."""
        return bool(self.focal_scale_sigma or self.focal_difference_sigma or self.baseline_scale_sigma
                    or self.boresight_sigma_deg)


class _ScenarioCore(_Strict):
    """A simulated traverse: the path, the world, the sensors and the estimator. A measurement
    kind with a simulated sensor (`Kind.Sensor`) adds its section, `[<kind>]` (Scenario below)."""

    # it names the results folder: no path separators or control characters
    name: str = Field(min_length=1, max_length=100, pattern=r"^[^\x00-\x1f/\\]+$")
    description: str = ""
    seed: int = Field(0, ge=0, lt=2**63)
    noise_seed: int | None = Field(
        None, ge=0, lt=2**63, description="another draw of the rover's measurement noise (pixels, tracking, ties, "
        "odometry, GPS, the start survey) over the same world, path, sites, calibration and mast pointing: how much "
        "one traverse's result owes to its noise (docs/simulation_errors.md); none: the seed's own")
    rig: Literal["exomars", "mer_navcam", "mer_pancam", "prototype"] = "exomars"
    origin: OriginConfig
    path: PathConfig
    terrain: TerrainConfig = TerrainConfig()
    camera: CameraConfig = CameraConfig()
    sites: SitesConfig = SitesConfig()
    gps: GpsConfig = GpsConfig()
    dead_reckoning: DeadReckoningConfig = DeadReckoningConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    render: RenderConfig = RenderConfig()
    errors: SimulationErrors = SimulationErrors()

    @model_validator(mode="before")
    @classmethod
    def _realistic_estimator(cls, data):
        """The estimator knows the statistics of the errors [errors] draws, not the draws: under the
        realistic profile it estimates the calibration, with the matcher's ties it weights a tie's
        views by the matcher's measured error, and with the mast's resolution an HRC view by its
        pointing error, unless it says otherwise."""
        if not isinstance(data, dict) or not isinstance(data.get("errors"), dict):
            return data
        estimator = data.get("estimator", {})
        if not isinstance(estimator, dict):
            return data
        try:  # the table as the profile resolves it; a bad one is reported by its own field
            errors = SimulationErrors.model_validate(data["errors"])
        except ValidationError:
            return data
        if errors.profile == "realistic" and estimator.get("calibration", "auto") == "auto":
            estimator = {**estimator, "calibration": "estimated"}
        sites = estimator.get("sites", {})
        if errors.tie_matching == "measured" and isinstance(sites, dict) and sites.get("tie_error") is None:
            estimator = {**estimator, "sites": {**sites, "tie_error": "measured"}}
        if errors.stereo_tracking == "measured" and estimator.get("vo_sigma_scale") is None:
            estimator = {**estimator, "vo_sigma_scale": TRACKED_VO_SIGMA_SCALE}
        hrc = estimator.get("hrc", {})
        if errors.pan_tilt_resolution_deg > 0 and isinstance(hrc, dict) and hrc.get("pointing_sigma_deg") is None:
            # a reading within half the resolution, uniform
            estimator = {**estimator, "hrc": {**hrc, "pointing_sigma_deg": errors.pan_tilt_resolution_deg
                                              / math.sqrt(12.0)}}
        return {**data, "estimator": estimator}

    @model_validator(mode="after")
    def _kinds_rules(self) -> _ScenarioCore:
        """Each kind's own rules for a scenario (Kind.check_scenario: GPS on Mars, the sun's planet)."""
        for kind in KINDS.values():
            kind.check_scenario(self)
        return self


Scenario = create_model("Scenario", __base__=_ScenarioCore, __module__=__name__, **_kind_sections("Sensor"))


def _describe(err: dict) -> str:
    field = ".".join(str(p) for p in err["loc"]) or "(top level)"
    if err["type"] == "extra_forbidden":
        return f"field '{field}': unknown key"
    got = err.get("input")
    got_text = f" (got {_shortened(repr(got))})" if got is not None and not isinstance(got, dict) else ""
    return f"field '{field}': {err['msg'].removeprefix('Value error, ')}{got_text}"


def _with_calibration(kinds):
    """A configuration that measures through the stereo pair (VO or sites) with the pair's
    calibration estimated: stereo_calibration builds its VO steps' factors, in place of vo_scale's."""
    if not isinstance(kinds, list | tuple) or not {"vo", "sites"} & set(kinds):
        return kinds
    kinds = [k for k in kinds if k != "vo_scale"]
    return kinds if "stereo_calibration" in kinds else [*kinds, "stereo_calibration"]


def _with_shared_scale(kinds):
    """vo_scale added to a configuration with VO, unless it has it or the estimated calibration,
    whose VO factors model the scale (and the turn) in its place (_with_calibration)."""
    if not isinstance(kinds, list | tuple) or "vo" not in kinds or {"vo_scale", "stereo_calibration"} & set(kinds):
        return kinds
    return [*kinds, "vo_scale"]


def with_vo_error_model(estimator: M, name: str) -> M:
    """The estimator with another VO error model: what its own model set gives way to the new
    model's (the defaults, for pixel_noise; the shared scale it added leaves the configurations)."""
    if name not in VO_ERROR_MODELS:
        raise ConfigError(f"vo_error_model {name!r}: expected {' or '.join(VO_ERROR_MODELS)}")
    given = estimator.model_dump(exclude_unset=True)
    for key, value in VO_ERROR_MODELS[estimator.vo_error_model].items():
        if isinstance(value, dict) and isinstance(given.get(key), dict):
            given[key] = {k: v for k, v in given[key].items() if k not in value}
        else:
            given.pop(key, None)
    if estimator.vo_error_model in SHARED_SCALE_MODELS and "configurations" in given:
        given["configurations"] = {n: [k for k in kinds if k != "vo_scale"]
                                   for n, kinds in given["configurations"].items()}
    return type(estimator).model_validate({**given, "vo_error_model": name})


def _shortened(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def validation_problems(exc: ValidationError) -> str:
    """A model's validation errors on one line: each field named, with what was expected."""
    problems = [_describe(e) for e in exc.errors()]
    return problems[0] if len(problems) == 1 else f"{len(problems)} problems: " + "; ".join(problems)


def load_toml_model(path: str | Path, model: type[M], what: str, error: type[PancamGraphError] = ConfigError,
                    tables: dict | None = None) -> M:
    """Read and validate a TOML file against a pydantic model, with `tables` in place of the
    file's tables of those names; every problem names the file and the field, raised as `error`."""
    path = Path(path)
    text = read_text(path, what, error)
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, ValueError) as exc:  # ValueError: an integer of thousands of digits
        raise error(f"{path}: not valid TOML: {exc}") from None
    try:
        return model.model_validate({**data, **(tables or {})})
    except ValidationError as exc:
        raise error(f"{path}: invalid {what}: {validation_problems(exc)}") from None


def load_scenario(path: str | Path, errors: str | None = None) -> Scenario:
    """Read and validate a scenario TOML file; every problem names the file and the field.
    `errors`: an error profile in place of the file's [errors] table (`run --errors`): the
    estimator then takes the defaults that profile sets, not those the file's table set."""
    check_error_profile(errors)
    return load_toml_model(path, Scenario, "scenario file", tables=None if errors is None else
                           {"errors": {"profile": errors}})


def bundled_scenarios() -> dict[str, Path]:
    folder = resources.files("pancam_graph.scenarios")
    return {Path(p.name).stem: Path(str(p)) for p in folder.iterdir() if p.name.endswith(".toml")}


def resolve_scenario(name_or_path: str) -> Path:
    """A bundled scenario name (e.g. `denver_trail`) or a path to a TOML file."""
    candidate = Path(name_or_path)
    bundled = bundled_scenarios()
    if candidate.is_dir() and name_or_path in bundled:
        return bundled[name_or_path]  # a folder of that name here (a render's images) is no scenario
    if candidate.suffix == ".toml" or candidate.exists():
        if candidate.is_dir():
            raise ConfigError(f"{candidate}: a folder, not a scenario TOML file")
        if not candidate.is_file():
            raise ConfigError(f"{candidate}: scenario file not found")
        return candidate
    if name_or_path not in bundled and ("/" in name_or_path or "\\" in name_or_path):
        raise ConfigError(f"{name_or_path}: no such file or folder")
    if name_or_path not in bundled:
        raise ConfigError(f"unknown scenario {name_or_path!r}; bundled: {', '.join(sorted(bundled))}")
    return bundled[name_or_path]


def dump_scenario(scenario: Scenario) -> str:
    """The scenario as TOML a user can read: each field's description as a comment above it, each
    [errors] magnitude with its realistic value's source, and arrays of numbers on one line (a
    waypoint a line, not a number a line)."""
    text = _one_line_arrays(tomli_w.dumps(scenario.model_dump(mode="json", exclude_none=True)))
    lines, section, model = [], "", Scenario
    for line in text.splitlines():
        if line.startswith("["):
            section = line.strip()
            model = _section_model(section.strip("[]"))
            lines += _comment(_purpose(model))
        key = line.split(" = ")[0]
        field = model.model_fields.get(key) if model is not None and " = " in line else None
        if field is not None and field.description:
            lines += _comment(field.description)
        if section == "[errors]" and key in REALISTIC_ERRORS:
            value, source = REALISTIC_ERRORS[key]
            line += f"  # realistic: {value!r}, from {source}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def _comment(text: str) -> list[str]:
    return [f"# {row}" for row in textwrap.wrap(" ".join(text.split()), 96)]


def _purpose(model: type[BaseModel] | None) -> str:
    """A table's model's docstring, its first sentence, without the table's name (on the next line)."""
    first = (model.__doc__ or "").strip().split("\n\n")[0].split(". ")[0] if model is not None else ""
    first = re.sub(r"^(A scenario's )?\[[\w.]+\]:?\s*", "", first)
    return first[:1].upper() + first[1:]


_NUMBER_ARRAY = re.compile(r"\[\n((?: +[^\[\]\n]+,\n)+) *\]")


def _one_line_arrays(text: str) -> str:
    """tomli_w's arrays of scalars (one item a line) written on one line each."""
    return _NUMBER_ARRAY.sub(lambda m: "[" + ", ".join(item.strip().rstrip(",")
                                                        for item in m.group(1).splitlines()) + "]", text)


def _section_model(dotted: str) -> type[BaseModel] | None:
    """The pydantic model of a TOML table (`path`, `kinds.gps`), None where it is not one."""
    model: type[BaseModel] | None = Scenario
    for part in dotted.split("."):
        field = model.model_fields.get(part) if model is not None else None
        if field is None:
            return None
        candidates = [field.annotation, *typing.get_args(field.annotation)]
        model = next((c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)), None)
    return model
