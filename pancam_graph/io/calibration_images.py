"""A folder of control-field stereo pairs, calibrated: every `NAME_left.png` with its
`NAME_right.png` (at any depth), the field's surveyed targets, the targets found in each
image and the fitted pair. Each image that cannot be read is named."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2

from ..errors import InputError
from ..frontend.calibrate import ControlField, Detections, StereoFit, calibrate_stereo, detect_targets
from .calibration import read_control_field

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm")


@dataclass
class FolderCalibration:
    fit: StereoFit
    field: ControlField
    pairs: list[tuple[Path, Path]]
    left: list[Detections]
    right: list[Detections]


def stereo_pairs(folder: Path) -> list[tuple[Path, Path]]:
    """(left, right) image paths, sorted; a left image without its right is an error."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder of calibration images")
    pairs = []
    for left in sorted(p for p in folder.rglob("*_left.*") if p.suffix.lower() in IMAGE_SUFFIXES):
        right = left.with_name(left.name.replace("_left.", "_right.", 1))
        if not right.is_file():
            raise InputError(f"{left}: no right image {right.name} beside it")
        pairs.append((left, right))
    if not pairs:
        raise InputError(f"{folder}: no stereo pairs (NAME_left.png with NAME_right.png) in it or below it")
    return pairs


def calibrate_folder(folder: Path, field_path: Path | None = None,
                     progress: Callable[[str, int, int], None] | None = None) -> FolderCalibration:
    """Find the field's targets in every pair under `folder` and calibrate the pair;
    `field_path` defaults to FOLDER/control_field.csv."""
    folder = Path(folder)
    field = read_control_field(field_path or folder / "control_field.csv")
    pairs = stereo_pairs(folder)
    size = None
    left, right = [], []
    for i, pair in enumerate(pairs):
        for path, found in zip(pair, (left, right), strict=True):
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise InputError(f"{path}: not an image OpenCV can read")
            if size is None:
                size = (image.shape[1], image.shape[0])
            elif (image.shape[1], image.shape[0]) != size:
                raise InputError(f"{path}: {image.shape[1]} x {image.shape[0]} px, the first image is {size[0]} x "
                                 f"{size[1]}")
            found.append(detect_targets(image, field))
        if progress is not None:
            progress("targets", i + 1, len(pairs))
    names = [str(p[0].relative_to(folder)) for p in pairs]
    return FolderCalibration(calibrate_stereo(field, left, right, size, names), field, pairs, left, right)
