"""A KITTI odometry sequence folder (stereo images, calib.txt, optional times and poses) as a
traverse: the image front-end runs over every frame and hands the back-end its stereo
observations; the poses, when given, are the reference. A car's stereo pair is fixed to its
body: `body_T_nav_left` puts the left camera at the body origin looking forward."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import REAL_IMAGE_ROTATION_FLOOR_DEG_PER_M, EstimatorConfig, FrontendConfig
from ..errors import InputError
from ..frontend.tracker import StereoTracker
from ..geodesy import LocalFrame
from ..records import GroundTruth, SlipPrior, StereoObservations, Stop, Traverse
from ..rig import BODY_T_FORWARD_CAMERA, Rig
from ..solve.results import SourceData, SourceInfo
from ..source_options import SourceOptions
from .frames import median_frame_ms, track_frames
from .registry import Source, frontend_for

# Matching and localisation error of the front-end's features (1 sigma).
PIXEL_SIGMA_PX = 0.5

# The VO error model for real images, measured on the 51 real KITTI frames of
# shared/data/real/kitti_odometry_51 (docs/frontend.md): per 1.2 m step the two-stop
# adjustment's covariance explained a median NEES of 203 (6 dof); the errors per metre were
# forward +0.76 % mean (a scale bias: the vo_scale kind), lateral 0.27 +- 0.44 %, vertical
# -0.41 +- 0.19 % (biases of the motion's direction, covered here as white noise), rotation
# 0.02-0.03 deg/m RMS per axis. Features beyond 40 m (disparity below 10 px) biased the scale.
REAL_IMAGE_ESTIMATOR = EstimatorConfig(
    vo_max_range_m=40.0,
    vo_translation_floor=0.012,
    vo_rotation_floor_deg_per_m=REAL_IMAGE_ROTATION_FLOOR_DEG_PER_M,
    vo_scale={"sigma": 0.01},
    configurations={"vo": ["vo", "vo_scale"]},
)


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
        traverse_tilt_rad=0.0, image_noise_px=PIXEL_SIGMA_PX, gps_lever_arm_m=np.zeros(3),
        start_world_T_body=start, start_sigmas=np.array([1e-4] * 3 + [1e-3] * 3),
        wheel_slip=SlipPrior(), body_T_nav_left=BODY_T_FORWARD_CAMERA,
    )
    info = SourceInfo("kitti_odometry", str(sequence.folder), "poses.txt (KITTI ground truth)" if truth else "none",
                      notes=("no geodetic origin: the local frame is the first camera's, WGS84 exports are "
                             "placeholders at 0 N 0 E",
                             f"front-end {frontend.detector}: median {median_frame_ms(tracker):.1f} ms per frame",
                             *notes),
                      options={"detector": frontend.detector},
                      axes=("forward of the first pose", "left of the first pose"))
    return SourceData(traverse, truth, REAL_IMAGE_ESTIMATOR, 0, info)


def _load(text: str, options: SourceOptions, progress) -> SourceData:
    frontend = frontend_for(options)
    return load(Path(text), frontend, progress, bool(options.skip_bad_frames))


SOURCES = (Source("kitti_odometry", 50, frozenset({"detector", "skip_bad_frames"}), matches, _load,
                  "a KITTI odometry sequence (calib.txt with image_0/image_1 or image_l/image_r)"),)
