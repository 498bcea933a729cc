"""A KITTI odometry sequence folder (stereo images, calib.txt, optional times and poses) as a
traverse: the image front-end runs over every frame and hands the back-end its stereo
observations; the poses, when given, are the reference. A car's stereo pair is fixed to its
body: `body_T_nav_left` puts the left camera at the body origin looking forward."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import EstimatorConfig, FrontendConfig, SourceOptions
from ..errors import InputError
from ..frontend.tracker import StereoTracker
from ..geometry.geodesy import LocalFrame
from ..geometry.rig import BODY_T_FORWARD_CAMERA, Rig
from ..records import GroundTruth, SlipPrior, StereoObservations, Stop, Traverse
from ..solve.results import SourceInfo
from .frames import median_frame_ms, track_frames
from .registry import Source, SourceData, StereoFrames, frontend_for

# The real KITTI frames' own VO error model (config.VO_ERROR_MODELS, docs/frontend.md, where it was
# measured): with no sites or GPS, the one configuration is vo with its shared scale.
REAL_IMAGE_ESTIMATOR = EstimatorConfig(vo_error_model="real_images", configurations={"vo": ["vo", "vo_scale"]})


def matches(path: Path) -> bool:
    from ..formats.kitti import is_kitti_odometry

    return is_kitti_odometry(path)


def load(folder: Path, frontend: FrontendConfig | None = None,
         progress: Callable[[str, int, int], None] | None = None, skip_bad_frames: bool = False) -> SourceData:
    from ..formats.kitti import read_kitti_odometry

    sequence = read_kitti_odometry(folder)
    frontend = frontend or FrontendConfig()
    tracker = StereoTracker(frontend)
    size = (sequence.stereo.camera.height, sequence.stereo.camera.width)

    def read_pair(k: int) -> tuple[np.ndarray, np.ndarray]:
        left, right = sequence.stereo_pair(k)
        for path, image in ((sequence.left_images[k], left), (sequence.right_images[k], right)):
            if image.shape != size:
                raise InputError(f"{path}: {image.shape[1]} x {image.shape[0]} px, but the calibration (and the "
                                 f"first left image) is {size[1]} x {size[0]}")
        return left, right

    stops = [Stop(k, float(sequence.times_s[k]), StereoObservations.empty()) for k in range(len(sequence))]
    return track_frames(stops, read_pair, tracker,
                        lambda tracked, notes: traverse_from_sequence(sequence, tracked, tracker, frontend, notes),
                        skip_bad_frames, progress)


def traverse_from_sequence(sequence, stops: list[Stop], tracker: StereoTracker, frontend: FrontendConfig,
                           notes: list[str] = ()) -> SourceData:
    """The traverse of the stops tracked (the first len(stops) frames of the sequence)."""
    from ..formats.kitti import FEATURE_SIGMA_PX

    cam = sequence.stereo.camera
    rig = Rig(f"kitti {sequence.folder.name}", cam, sequence.stereo.baseline_m, mast_height_m=1.65)
    truth = None
    if sequence.world_T_camera is not None:  # camera poses in the first camera's frame
        body = BODY_T_FORWARD_CAMERA
        world_T_camera = sequence.world_T_camera[:len(stops)]
        truth = GroundTruth(body @ world_T_camera @ np.linalg.inv(body), np.zeros((0, 3)))
    start = np.eye(4) if truth is None else truth.world_T_body[0]
    traverse = Traverse(
        name=sequence.folder.name, rig=rig, origin=LocalFrame(0.0, 0.0, 0.0), stops=tuple(stops),
        traverse_tilt_rad=0.0, image_noise_px=FEATURE_SIGMA_PX, gps_lever_arm_m=np.zeros(3),
        start_world_T_body=start, start_sigmas=np.array([1e-4] * 3 + [1e-3] * 3),
        wheel_slip=SlipPrior(), body_T_nav_left=BODY_T_FORWARD_CAMERA,
    )
    info = SourceInfo("kitti_odometry", str(sequence.folder), "poses.txt (KITTI ground truth)" if truth else "none",
                      georeferenced=False,
                      notes=("no geodetic origin: the local frame is the first camera's, so no geographic file "
                             "(WGS84 CSV, GeoJSON, KML) is written",
                             f"front-end {frontend.detector}: median {median_frame_ms(tracker):.1f} ms per frame",
                             *notes),
                      options={"detector": frontend.detector},
                      axes=("forward of the first pose", "left of the first pose"))
    return SourceData(traverse, truth, REAL_IMAGE_ESTIMATOR, 0, info)


def stereo_frames(folder: Path) -> StereoFrames:
    from ..formats.kitti import read_kitti_odometry

    sequence = read_kitti_odometry(folder)
    cam = sequence.stereo.camera
    stops = [Stop(k, float(sequence.times_s[k]), StereoObservations.empty()) for k in range(len(sequence))]
    return StereoFrames(stops, sequence.stereo_pair, (cam.height, cam.width))


def _load(text: str, options: SourceOptions, progress) -> SourceData:
    frontend = frontend_for(options)
    return load(Path(text), frontend, progress, bool(options.skip_bad_frames))


SOURCES = (Source("kitti_odometry", 50, frozenset({"detector", "skip_bad_frames"}), matches, _load,
                  "a KITTI odometry sequence (calib.txt with image_0/image_1 or image_l/image_r)",
                  frames=stereo_frames, estimator=lambda text: REAL_IMAGE_ESTIMATOR),)
