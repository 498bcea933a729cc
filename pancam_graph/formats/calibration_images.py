"""A folder of control-field stereo pairs, calibrated: every `NAME_left.png` with its
`NAME_right.png` (at any depth) and the field's surveyed targets, into the fitted pair. Each
image that cannot be read is named."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import InputError
from ..frontend.calibrate import StereoFit, calibrate_stereo, detect_targets
from .calibration import read_control_field
from .images import read_gray

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm")
FIELD_FILE = "control_field.csv"  # the field's surveyed targets, beside the images
TRUTH_FILE = "truth_calibration.yaml"  # a rendered field's true calibration


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
                     progress: Callable[[str, int, int], None] | None = None) -> StereoFit:
    """Find the field's targets in every pair under `folder` and calibrate the pair;
    `field_path` defaults to FOLDER/control_field.csv."""
    folder = Path(folder)
    field = read_control_field(field_path or folder / FIELD_FILE)
    pairs = stereo_pairs(folder)
    size = None
    left, right = [], []
    for i, pair in enumerate(pairs):
        for path, found in zip(pair, (left, right), strict=True):
            image = read_gray(path, size and (size[1], size[0]), f"the first image ({pairs[0][0].name})")
            size = size or (image.shape[1], image.shape[0])
            found.append(detect_targets(image, field))
        if progress is not None:
            progress("targets", i + 1, len(pairs))
    names = [str(p[0].relative_to(folder)) for p in pairs]
    return calibrate_stereo(field, left, right, size, names)
