"""Orbital-map registration: where there is no GPS (Mars), the absolute reference is the orbital
map, a DTM at about 1 m posts (HiRISE stereo) and its orthoimage.

At every site the panorama's triangulated points, a local elevation map, are registered to the
DTM from the predicted pose (dem_registration.py): the rover's horizontal position and heading
in the map's frame, with the fit's covariance; and its height, against the DTM's. A map's
georeference is itself off by a few metres, a small rotation and a datum offset in height, the
same for every site it serves; treated as white noise per site, that error would pull the whole
traverse by the map's offset while the covariance shrank as if it averaged away. So each map
has a bias variable, four shared scalars (east, north, up, and the rotation about the local
origin: maps.MapBias) with a prior from the map's stated accuracy, and each registration is a
factor on the site's pose and its map's bias: the same idea as the VO scale and the wheel slip.
Before it goes in, a registration must agree with the predicted pose (Mahalanobis, chi-square
with 4 dof at `gate_probability`); the refused are reported.

Where the rover's images are at hand (runs on image folders), the site's ground seen from above
(records.GroundPatch, from its panorama's dense stereo) is also correlated with the map's
orthoimage (ortho_registration.py): the rover's east and north in the map's frame, a second
factor on the same pose and bias, gated at chi-square with 2 dof.

Neighbouring sites see overlapping parts of the map (their points reach 40 m, and sites are
30-60 m apart), so their registration errors are correlated: +0.1 to +0.3 one site apart and
none further (docs/orbital.md, "The map's bias"). Averaged as if independent, they made the map
bias about 1.2 times over-confident over 10 km. So the errors are a moving average: each pair of
consecutive registrations (of one map, at most `neighbour_m` apart) shares an error variable,
a 4-vector E(k) with a prior of `neighbour_correlation` times the registration's covariance, and
each registration keeps the rest of its covariance as its own. A registration's variance stays
what its fit says, and its neighbours' errors have the stated correlation.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from pydantic import Field

from ..errors import InputError
from ..graph import chi2, keys, tie_gate
from ..graph.keys import E, X
from ..orbital.dem_registration import (
    DtmErrors,
    MapNotCovering,
    RegistrationFailed,
    register_site,
    yaw_jacobian,
    yaw_of,
)
from ..orbital.maps import MapBias, ground_spacing, hillshade, sampled_raster
from ..orbital.ortho_registration import register_patch
from ..records import GroundTruth, MapRaster, OrbitalMap, Stop, Traverse
from .base import Kind, Section

BIAS_NAMES = ("east_m", "north_m", "up_m", "rotation_rad")
MAX_MAPS = 100  # maps of one traverse: each has its bias, 4 shared scalars
_BIAS_KEYS = keys.shared("orbital", len(BIAS_NAMES) * MAX_MAPS)


def bias_keys(map_index: int) -> tuple[int, int, int, int]:
    """The shared variables of map `map_index`'s bias: east, north, up (m), rotation (rad)."""
    first = len(BIAS_NAMES) * map_index
    return _BIAS_KEYS[first:first + len(BIAS_NAMES)]


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def predicted_measurement(pose, bias: np.ndarray, jacobians: list | None = None) -> np.ndarray:
    """(east, north, up, yaw) of the body in the map's frame, from its pose (gtsam.Pose3) in the
    world and the map's bias (east, north, up, rotation); `jacobians` gets d/d pose (4x6, GTSAM's
    [rotation, translation] right perturbation) and d/d each bias scalar (4x1)."""
    rotation = pose.rotation().matrix()
    position = pose.translation()
    c, s = np.cos(bias[3]), np.sin(bias[3])
    turn = np.array([[c, -s], [s, c]])
    out = np.array([*(turn @ position[:2] + bias[:2]), position[2] + bias[2], yaw_of(rotation) + bias[3]])
    if jacobians is not None:
        d_pose = np.zeros((4, 6))
        d_pose[:2, 3:] = turn @ rotation[:2, :]
        d_pose[2, 3:] = rotation[2, :]
        d_pose[3, :3] = yaw_jacobian(rotation)
        jacobians[0] = d_pose
        for i in range(3):
            jacobians[1 + i] = np.eye(4)[:, [i]]
        jacobians[4] = np.array([*(np.array([[-s, -c], [c, -s]]) @ position[:2]), 0.0, 1.0]).reshape(4, 1)
    return out


def orbital_error(measured: np.ndarray, pose, bias: np.ndarray, jacobians: list | None = None,
                  shared: tuple[np.ndarray, ...] = ()) -> np.ndarray:
    """Predicted minus measured (east, north, up, yaw), the yaw wrapped; the errors `shared` with
    the neighbouring sites add to the prediction (`jacobians` gets the identity for each)."""
    error = predicted_measurement(pose, bias, jacobians) - measured + sum(shared, np.zeros(4))
    error[3] = _wrap(error[3])
    if jacobians is not None:
        for i in range(len(shared)):
            jacobians[5 + i] = np.eye(4)
    return error


def orbital_factor(stop: int, map_index: int, measured: np.ndarray, covariance: np.ndarray,
                   shared: tuple[int, ...] = (), components: tuple[int, ...] = (0, 1, 2, 3)):
    """A site's registration to map `map_index`: a factor on its pose, the map's bias and the
    errors it shares with its neighbouring sites' registrations (E keys); `covariance` is its
    own part. `components`: which of (east, north, up, yaw) it measures (an orthoimage's
    correlation: east and north), `measured` and `covariance` being theirs."""
    rows = list(components)
    full = np.zeros(4)
    full[rows] = measured

    def error(factor, values, jacobians):
        pose_key, *keys = factor.keys()
        bias = np.array([values.atDouble(k) for k in keys[:4]])
        all_jacobians = None if jacobians is None else [None] * len(jacobians)
        out = orbital_error(full, values.atPose3(pose_key), bias, all_jacobians,
                            tuple(values.atVector(k) for k in keys[4:]))
        if jacobians is not None:
            for i, jacobian in enumerate(all_jacobians):
                jacobians[i] = jacobian[rows]
        return out[rows]

    model = gtsam.noiseModel.Gaussian.Covariance(0.5 * (covariance + covariance.T))
    return gtsam.CustomFactor(model, [X(stop), *bias_keys(map_index), *shared], error)


@dataclass(frozen=True)
class _Neighbour:
    """A map's last registration: where its site is and the error the next one may share."""

    position: np.ndarray  # east, north (m) as estimated then
    shared_key: int


class OrbitalSettings(Section):
    """[estimator.orbital]: how sites are registered to the orbital maps."""

    gate_probability: float = Field(0.999, gt=0.5, lt=1.0, description="chi-square (4 dof) level of the "
                                    "registration's agreement with the predicted pose above which it is refused")
    max_range_m: float = Field(40.0, gt=2.0, le=200.0, description="site points used, out to this horizontal range")
    min_points: int = Field(30, ge=6, description="fewer site points than this: no registration")
    min_distinctness: float = Field(50.0, ge=0.0, description="how much worse (summed squared weighted residuals) "
                                    "the best other place more than 2 m away must fit; less: ambiguous, not used")
    surface_sigma_m: float = Field(0.25, gt=0.0, le=10.0, description="a point's ground against the DTM's surface "
                                   "(rocks, the DTM's resolution), independent per point")
    dtm_sigma_m: float = Field(0.15, ge=0.0, le=10.0, description="the DTM's own height error and what its "
                               "smoothing takes off the relief, shared by nearby points")
    dtm_correlation_m: float = Field(3.0, gt=0.0, le=100.0, description="distance over which that error is shared")
    search_sigmas: float = Field(3.0, gt=0.0, le=10.0, description="horizontal search around the prediction, in "
                                 "its standard deviations")
    search_m: tuple[float, float] = Field((2.0, 15.0), description="least and largest horizontal search (m)")
    neighbour_correlation: float = Field(0.25, ge=0.0, lt=0.5, description="correlation of consecutive sites' "
                                         "registration errors (overlapping parts of the map); 0: independent")
    neighbour_m: float = Field(80.0, gt=0.0, le=1000.0, description="consecutive sites further apart than this "
                               "share no error (about twice `max_range_m`: their points no longer overlap)")
    use_orthoimage: bool = Field(True, description="also correlate a site's ground, where its images give it "
                                 "(runs on image folders), with the map's orthoimage")


class OrbitalSensor(Section):
    """A scenario's [orbital]: the orbital map a simulation makes of its terrain."""

    enabled: bool = False
    post_m: float = Field(1.0, gt=0.1, le=20.0, description="DTM post spacing (HiRISE: 1 m)")
    margin_m: float = Field(80.0, ge=0.0, le=1000.0, description="map beyond the traverse's box")
    offset_sigma_m: float = Field(3.0, ge=0.0, le=100.0, description="1-sigma georeference offset, per axis")
    vertical_sigma_m: float = Field(1.0, ge=0.0, le=100.0, description="1-sigma offset of its heights (its datum)")
    rotation_sigma_deg: float = Field(0.02, ge=0.0, le=5.0, description="1-sigma georeference rotation")
    dtm_noise_m: float = Field(0.1, ge=0.0, le=10.0, description="1-sigma DTM height error, smooth over "
                               "`noise_correlation_posts`")
    noise_correlation_posts: float = Field(2.0, gt=0.0, le=50.0)
    smoothing_posts: float = Field(1.0, ge=0.0, le=20.0, description="the stereo's smoothing of the relief (posts)")
    orthoimage_pixel_m: float = Field(0.5, ge=0.0, le=20.0, description="orthoimage pixel (HiRISE: 0.25-0.5 m); "
                                      "0: none")
    sun_azimuth_deg: float = Field(135.0, ge=0.0, lt=360.0, description="the orthoimage's sun, not the rover's")
    sun_elevation_deg: float = Field(35.0, gt=0.0, le=90.0)


class Orbital(Kind):
    name = "orbital"
    order = 8
    absolute = True
    cost = 0.5
    MAX_MAP_LATITUDE_DEG = 80.0  # the equirectangular map projection a simulated map uses degenerates at a pole

    @classmethod
    def check_scenario(cls, scenario) -> None:
        sensor = getattr(scenario, cls.name, None)
        if sensor is not None and sensor.enabled and abs(scenario.origin.lat_deg) > cls.MAX_MAP_LATITUDE_DEG:
            raise ValueError(f"[orbital] at latitude {scenario.origin.lat_deg:g}: a simulated orbital map is "
                             f"equirectangular, which holds within {cls.MAX_MAP_LATITUDE_DEG:g} deg of the equator "
                             "(polar stereographic maps are not made here)")
    stop_records = frozenset({"ground"})
    Settings = OrbitalSettings
    Sensor = OrbitalSensor
    step_counters = {"orbital_registrations": 0, "orbital_refused": 0}
    counter_defaults = {"orbital_registrations_used": 0, "orbital_ortho_registrations_used": 0,
                        "orbital_registrations_refused": 0,
                        "orbital_uncovered_stops": [], "orbital_failed_stops": [], "orbital_bias": [],
                        "orbital_bias_sigma": [], "orbital_seconds_per_site": 0.0}

    warning_counters = {"orbital_uncovered_stops": "site stops no orbital map covers (not registered)",
                        "orbital_failed_stops": "sites not registered to an orbital map"}

    records = "orbital maps"

    @classmethod
    def unavailable(cls, traverse: Traverse) -> str | None:
        if not traverse.measurements.get(cls.name):
            return "the traverse has no orbital maps"
        if not any(s.is_site for s in traverse.stops):
            return "the traverse has no site panoramas to register"
        return None

    # -- records -------------------------------------------------------------------------------

    @classmethod
    def simulate_with_truth(cls, sensor: OrbitalSensor, traverse: Traverse, truth: GroundTruth,
                            rng: np.random.Generator) -> tuple[tuple[OrbitalMap, ...], dict[str, float]]:
        """A map of the truth's terrain over the traverse's box, with a drawn georeference error,
        the orbiter's smoothing and a smooth height error; its orthoimage lit by its own sun."""
        from scipy.ndimage import gaussian_filter

        if truth.terrain is None:
            return (), {}
        offset = rng.normal(0.0, sensor.offset_sigma_m, 2)
        bias = MapBias(*offset, rng.normal(0.0, np.deg2rad(sensor.rotation_sigma_deg)))
        up = float(rng.normal(0.0, sensor.vertical_sigma_m))
        lo = truth.positions[:, :2].min(axis=0) - sensor.margin_m
        hi = truth.positions[:, :2].max(axis=0) + sensor.margin_m
        dtm = sampled_raster(truth.terrain, traverse.origin, lo, hi, sensor.post_m, bias)
        if sensor.smoothing_posts > 0:
            dtm.values[:] = gaussian_filter(dtm.values.astype(float), sensor.smoothing_posts)
        if sensor.dtm_noise_m > 0:
            noise = gaussian_filter(rng.normal(size=dtm.values.shape), sensor.noise_correlation_posts)
            dtm.values[:] += (sensor.dtm_noise_m / noise.std() * noise).astype(np.float32)
        dtm.values[:] += np.float32(up)
        orthoimage = None
        if sensor.orthoimage_pixel_m > 0:
            fine = sampled_raster(truth.terrain, traverse.origin, lo, hi, sensor.orthoimage_pixel_m, bias)
            shade = hillshade(fine.values, ground_spacing(fine), sensor.sun_azimuth_deg, sensor.sun_elevation_deg)
            grey = np.clip(40 + 200 * shade + rng.normal(0.0, 4.0, shade.shape), 0, 255).astype(np.uint8)
            orthoimage = MapRaster(grey, fine.x0_m, fine.y0_m, fine.post_m, fine.crs_wkt)
        orbital_map = OrbitalMap("orbital_map", dtm, orthoimage, sensor.offset_sigma_m, sensor.rotation_sigma_deg,
                                 sensor.vertical_sigma_m)
        state = {"map0_east_m": float(bias.east_m), "map0_north_m": float(bias.north_m), "map0_up_m": up,
                 "map0_rotation_rad": float(bias.rotation_rad)}
        return (orbital_map,), state

    # -- the step ------------------------------------------------------------------------------

    @classmethod
    def check_traverse(cls, traverse: Traverse) -> None:
        maps = traverse.measurements.get(cls.name, ())
        if len(maps) > MAX_MAPS:
            raise InputError(f"{len(maps)} orbital maps: at most {MAX_MAPS} in one traverse (merge them)")
        frame, start = traverse.origin, traverse.start_world_T_body[:3, 3]
        covering = []
        for orbital_map in maps:
            _check_map(orbital_map, frame)
            covering.append(np.isfinite(orbital_map.dtm.at(frame.to_map(start[None, :]))[0]))
        if maps and not any(covering):
            raise InputError(f"{maps[0].called} does not cover the traverse's start ({start[0]:.1f} m east, "
                             f"{start[1]:.1f} m north of the origin)")

    def __init__(self, localizer):
        super().__init__(localizer)
        settings: OrbitalSettings = localizer.estimator.orbital
        self.settings = settings
        self.errors = DtmErrors(settings.surface_sigma_m, settings.dtm_sigma_m, settings.dtm_correlation_m)
        self.gate = chi2.quantile(settings.gate_probability, 4)
        self.gate_2 = chi2.quantile(settings.gate_probability, 2)
        self.check_traverse(localizer.traverse)
        for m, orbital_map in enumerate(self.maps):
            sigmas = (orbital_map.offset_sigma_m, orbital_map.offset_sigma_m, orbital_map.vertical_sigma_m,
                      np.deg2rad(orbital_map.rotation_sigma_deg))
            for key, sigma in zip(bias_keys(m), sigmas, strict=True):
                prior = gtsam.noiseModel.Isotropic.Sigma(1, max(sigma, 1e-6))
                localizer.smoother.add(gtsam.PriorFactorDouble(key, 0.0, prior))
                localizer.smoother.insert(key, 0.0, shared=True)
        self._site: tuple | None = None  # (stop, points, ground) between update_before and add
        self.registrations: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # stop, map, measured, covariance
        self.refused: list[int] = []
        self.uncovered: list[int] = []
        self.failed: list[str] = []
        self.seconds: list[float] = []
        self.ortho_registrations: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # east, north only
        self.shared_errors: list[int] = []  # E keys, in order
        self._last: dict[int, _Neighbour] = {}  # by map

    @property
    def maps(self) -> tuple[OrbitalMap, ...]:
        """The traverse's maps (read through it: a checkpoint refers to the traverse, it does not
        copy its rasters)."""
        return self.loc.traverse.measurements.get(self.name, ())

    def update_before(self, stop: Stop) -> str | None:
        """A site with points or ground to register: the registration starts from the site's
        updated pose and reads its marginal."""
        self._site = None
        if not stop.is_site or not self.maps:
            return None
        # triangulated through the pair as calibrated now (a turn of the right camera by 0.02 deg
        # puts a point 40 m away about 1 m off in range: the elevation map's shape)
        points = tie_gate.site_point_cloud(stop, self.loc.traverse.rig, self.loc.traverse.image_noise_px,
                                           self.loc.site_stereo_pixels)
        if points is None:
            self.failed.append(f"stop {stop.index}: no triangulated site points")
        ground = stop.ground if self.settings.use_orthoimage else None
        if points is None and ground is None:
            return None
        self._site = (stop.index, points, ground)
        return "before its orbital registration"

    def add(self, stop: Stop, counts) -> None:
        site, self._site = self._site, None
        if site is None or site[0] != stop.index:
            return
        _, points, ground = site
        smoother = self.loc.smoother
        pose = smoother.pose(X(stop.index))
        covered = False
        for m, orbital_map in enumerate(self.maps):
            bias = np.array([smoother.estimate_double(k) for k in bias_keys(m)])
            if points is not None:
                covered |= self._register_to_dtm(stop.index, m, points, pose, bias, counts)
            if ground is not None and orbital_map.orthoimage is not None:
                covered |= self._register_to_orthoimage(stop.index, m, ground, pose, bias, counts)
        if not covered:
            self.uncovered.append(stop.index)

    def _prediction(self, stop: int, m: int, pose, bias: np.ndarray, shared: tuple[int, ...] = ()
                    ) -> tuple[np.ndarray, np.ndarray, float]:
        """The predicted registration to map `m` (east, north, up, yaw) with the errors `shared`
        with the last site added, its covariance, and the horizontal search it calls for."""
        smoother = self.loc.smoother
        jacobians = [None] * 5
        predicted = predicted_measurement(pose, bias, jacobians)
        for key in shared:
            predicted += smoother.vector(key)
            jacobians.append(np.eye(4))
        spread = np.hstack(jacobians)
        covariance = spread @ smoother.joint_marginal_covariance(X(stop), *bias_keys(m), *shared) @ spread.T
        search = np.clip(self.settings.search_sigmas * np.sqrt(np.linalg.eigvalsh(covariance[:2, :2]).max()),
                         *self.settings.search_m)
        return predicted, covariance, float(search)

    def _register_to_dtm(self, stop: int, m: int, points, pose, bias: np.ndarray, counts) -> bool:
        """The site's points registered to map `m`'s DTM, gated and added; False if the map
        does not cover the site."""
        smoother = self.loc.smoother
        orbital_map = self.maps[m]
        earlier = self._neighbour(m, pose)
        predicted, predicted_cov, search = self._prediction(stop, m, pose, bias, earlier)
        rotation = pose.rotation().matrix()
        vertical_var = np.einsum("i,nij,j->n", rotation[2], points[1], rotation[2])
        try:
            registration = register_site(points[0], vertical_var, _map_pose(pose, bias), orbital_map.dtm,
                                         self.loc.traverse.origin, search, self.errors, self.settings.max_range_m,
                                         self.settings.min_points, self.settings.min_distinctness)
        except MapNotCovering:
            return False
        except RegistrationFailed as exc:
            self.failed.append(f"stop {stop}, map {orbital_map.name!r}: {exc}")
            return True
        self.seconds.append(registration.seconds)
        innovation = registration.measurement - predicted
        innovation[3] = _wrap(innovation[3])
        rho = self.settings.neighbour_correlation
        unshared = (1.0 - rho * len(earlier)) * registration.covariance  # what the earlier one's error leaves
        d2 = float(innovation @ np.linalg.solve(unshared + predicted_cov, innovation))
        if d2 > self.gate:
            self.refused.append(stop)
            counts.add("orbital_refused")
            return True
        shared = earlier
        if rho > 0:
            key = E(len(self.shared_errors))
            smoother.insert(key, np.zeros(4), leaves_with=X(stop))
            prior = gtsam.noiseModel.Gaussian.Covariance(rho * registration.covariance)
            smoother.add(gtsam.PriorFactorVector(key, np.zeros(4), prior))
            self.shared_errors.append(key)
            self._last[m] = _Neighbour(pose.translation()[:2], key)
            shared = (*earlier, key)
        own = (1.0 - rho * len(shared)) * registration.covariance
        arguments = (stop, m, registration.measurement, own, shared)
        smoother.add(orbital_factor(*arguments), rebuild=(orbital_factor, arguments))
        self.registrations.append((stop, m, registration.measurement, registration.covariance))
        counts.add("orbital_registrations")
        return True

    def _register_to_orthoimage(self, stop: int, m: int, ground, pose, bias: np.ndarray, counts) -> bool:
        """The site's ground patch correlated with map `m`'s orthoimage, gated and added (east
        and north); False if the orthoimage does not cover the site."""
        orbital_map = self.maps[m]
        predicted, predicted_cov, search = self._prediction(stop, m, pose, bias)
        try:
            found = register_patch(ground, _map_pose(pose, bias), orbital_map.orthoimage, self.loc.traverse.origin,
                                   search)
        except MapNotCovering:
            return False
        except RegistrationFailed as exc:
            self.failed.append(f"stop {stop}, map {orbital_map.name!r}'s orthoimage: {exc}")
            return True
        innovation = found.measurement - predicted[:2]
        if float(innovation @ np.linalg.solve(found.covariance + predicted_cov[:2, :2], innovation)) > self.gate_2:
            self.refused.append(stop)
            counts.add("orbital_refused")
            return True
        arguments = (stop, m, found.measurement, found.covariance, (), (0, 1))
        self.loc.smoother.add(orbital_factor(*arguments), rebuild=(orbital_factor, arguments))
        self.ortho_registrations.append((stop, m, found.measurement, found.covariance))
        counts.add("orbital_registrations")
        return True

    def _neighbour(self, m: int, pose) -> tuple[int, ...]:
        """The error this site's registration to map `m` shares with the map's last one: its key,
        or nothing if that one is too far away or its error left the smoother's window."""
        last = self._last.get(m)
        if last is None or not self.loc.smoother.live(last.shared_key):
            return ()
        if np.hypot(*(pose.translation()[:2] - last.position)) > self.settings.neighbour_m:
            return ()
        return (last.shared_key,)

    # -- results -------------------------------------------------------------------------------

    def _bias(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        keys = bias_keys(m)
        estimate = np.array([self.loc.smoother.estimate_double(k) for k in keys])
        sigma = np.sqrt(np.diag(self.loc.smoother.joint_marginal_covariance(*keys)))
        return estimate, sigma

    def true_values(self, truth: GroundTruth, values) -> bool:
        state = truth.kinds.get(self.name)
        if state is None:
            return False
        for m in range(len(self.maps)):
            for key, name in zip(bias_keys(m), BIAS_NAMES, strict=True):
                values.insert(key, float(state[f"map{m}_{name}"]))
        for key in self.shared_errors:  # not drawn by the simulation: their prior's mean
            values.insert(key, np.zeros(4))
        return True

    def counters(self) -> dict:
        biases = [self._bias(m) for m in range(len(self.maps))]
        degrees = np.array([1.0, 1.0, 1.0, 180.0 / np.pi])
        return {"orbital_registrations_used": len(self.registrations),
                "orbital_ortho_registrations_used": len(self.ortho_registrations),
                "orbital_registrations_refused": len(self.refused),
                "orbital_uncovered_stops": self.uncovered, "orbital_failed_stops": self.failed,
                "orbital_bias": [(b * degrees).tolist() for b, _ in biases],  # per map: east, north, up m, rotation deg
                "orbital_bias_sigma": [(s * degrees).tolist() for _, s in biases],
                "orbital_seconds_per_site": float(np.median(self.seconds)) if self.seconds else 0.0}

    def against_truth(self, truth: GroundTruth) -> dict:
        """The map biases in their standard deviations off the drawn ones, and each registration's
        horizontal error against the true pose seen through the true bias."""
        state = truth.kinds.get(self.name)
        if state is None:
            return {}
        out: dict = {"orbital_bias_error_sigmas": []}
        true_biases = []
        for m in range(len(self.maps)):
            true = np.array([state[f"map{m}_{n}"] for n in BIAS_NAMES])
            estimate, sigma = self._bias(m)
            out["orbital_bias_error_sigmas"].append(((estimate - true) / sigma).tolist())
            true_biases.append(true)
        for name, registrations in (("registration", self.registrations), ("ortho", self.ortho_registrations)):
            errors, nees = [], []
            for stop, m, measured, covariance in registrations:
                truth_pose = gtsam.Pose3(truth.world_T_body[stop])
                error = predicted_measurement(truth_pose, true_biases[m])[:len(measured)] - measured
                if len(error) == 4:
                    error[3] = _wrap(error[3])
                errors.append(np.hypot(*error[:2]))
                nees.append(float(error @ np.linalg.solve(covariance, error)))
            if errors:
                out.update({f"orbital_{name}_error_median_m": float(np.median(errors)),
                            f"orbital_{name}_error_p95_m": float(np.percentile(errors, 95)),
                            f"orbital_{name}_nees_mean": float(np.mean(nees))})
        return out


def _map_pose(pose, bias: np.ndarray) -> np.ndarray:
    """The body's pose in the map's frame (4x4) with the map's bias (east, north, up, rotation)."""
    matrix = pose.matrix()
    c, s = np.cos(bias[3]), np.sin(bias[3])
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = matrix.copy()
    out[:3, :3] = turn @ matrix[:3, :3]
    out[:3, 3] = turn @ matrix[:3, 3] + bias[:3]
    return out


def _check_map(orbital_map: OrbitalMap, frame) -> None:
    """A map of the traverse's body, in a projected CRS, with data: InputError naming it if not."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_wkt(orbital_map.dtm.crs_wkt)
    except CRSError as exc:
        raise InputError(f"{orbital_map.called}: unreadable CRS ({exc})") from None
    radius = crs.ellipsoid.semi_major_metre if crs.ellipsoid is not None else float("nan")
    expected = frame.map_crs().ellipsoid.semi_major_metre
    if not np.isclose(radius, expected, rtol=0.01):
        raise InputError(f"{orbital_map.called}: its CRS is on a body of radius {radius:,.0f} m, the "
                         f"traverse is on {frame.body} ({expected:,.0f} m)")
    if not np.isfinite(orbital_map.dtm.values).any():
        raise InputError(f"{orbital_map.called}: its DTM has no data")
    ortho = orbital_map.orthoimage
    if ortho is not None:
        if CRS.from_wkt(ortho.crs_wkt) != crs:
            raise InputError(f"{orbital_map.called}: its orthoimage and DTM are in different CRSs")
        dtm_box = _box(orbital_map.dtm)
        ortho_box = _box(ortho)
        overlap = np.minimum(dtm_box[2:], ortho_box[2:]) - np.maximum(dtm_box[:2], ortho_box[:2])
        if np.any(overlap <= 0):
            raise InputError(f"{orbital_map.called}: its orthoimage and DTM do not overlap")


def _box(raster: MapRaster) -> np.ndarray:
    """(x_min, y_min, x_max, y_max) of a raster in map coordinates."""
    rows, cols = raster.values.shape
    return np.array([raster.x0_m, raster.y0_m - rows * raster.post_m, raster.x0_m + cols * raster.post_m, raster.y0_m])
