"""Image files read as the front-ends need them: 8-bit grey, checked whole and of the size the
calibration expects, or a message naming the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError


def read_gray(path: Path, size: tuple[int, int] | None = None, expected: str = "the calibration") -> np.ndarray:
    """A grayscale image; with `size`, of that (height, width), which is `expected`'s."""
    if not path.is_file():
        raise InputError(f"{path}: missing")
    data = path.read_bytes()
    if path.suffix.lower() == ".png" and not data.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82"):
        raise InputError(f"{path}: truncated PNG (no IEND chunk)")
    if path.suffix.lower() in (".jpg", ".jpeg") and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise InputError(f"{path}: truncated JPEG (no end marker)")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: not a readable image")
    if size is not None and image.shape != size:
        raise InputError(f"{path}: {image.shape[1]} x {image.shape[0]} px, but {expected} is "
                         f"{size[1]} x {size[0]}")
    return image
