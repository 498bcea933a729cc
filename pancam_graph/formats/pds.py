"""Mars rover image products in PDS3 (MER, MSL): what a label says of its image, read with pdr
(the Planetary Data Reader). The image's UTC time (START_TIME; the spacecraft clock is not
UTC), the camera and eye, the rover motion counter (SITE, DRIVE, POSE), the rover's onboard pose
in its site frame, the site's offset from the site before, the camera model (CAHVOR in the
rover navigation frame) and the sun's direction the mission computed in the site frame (onboard,
from the onboard attitude: a cross-check, never a measurement).

Frames, as the missions have them: a site frame is x north, y east, z down at the site's
origin; the rover navigation frame is x forward, y right, z down. An
ORIGIN_ROTATION_QUATERNION (s, x, y, z) turns vectors of the frame it describes into its
reference frame. `enu_T_site` and `BODY_R_ROVER` convert at the border to this project's
east-north-up world and x-forward, y-left, z-up body.
"""

from __future__ import annotations

import datetime as dt
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.cahvor import CameraModel
from . import pds4
from .rover_image import RoverImage, frame_pose

# a site frame (north, east, down) -> east, north, up; the rover frame (forward, right, down)
# -> the body frame (forward, left, up)
ENU_R_SITE = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
BODY_R_ROVER = np.diag([1.0, -1.0, -1.0])
LABEL_SUFFIXES = (".LBL", ".lbl")


def _group(label, name: str, path: Path):
    try:
        return label[name]
    except KeyError:
        raise InputError(f"{path}: no {name} in the label") from None


def _table(label, name: str, path: Path, required: bool = True):
    """A group of the label (a mapping), or None when it is absent and not `required`."""
    group = label.get(name)
    if group is None and not required:
        return None
    if not hasattr(group, "get") or not hasattr(group, "__getitem__"):
        raise InputError(f"{path}: no {name} group in the label" if group is None else
                         f"{path}: {name} is {group!r}, expected a GROUP")
    return group


def _vector(group, name: str, size: int, path: Path, where: str) -> np.ndarray:
    try:
        value = np.array(group[name], dtype=float)
    except KeyError:
        raise InputError(f"{path}: {where} has no {name}") from None
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{path}: {where} {name} is not {size} numbers: {group[name]!r}") from None
    if value.shape != (size,) or not np.all(np.isfinite(value)):
        raise InputError(f"{path}: {where} {name} is not {size} finite numbers: {group[name]!r}")
    return value


def _integer(group, name: str, path: Path, where: str, default=None) -> int:
    """A whole number of a label's group, or InputError naming it."""
    try:
        value = group[name] if default is None else group.get(name, default)
    except (KeyError, TypeError):
        raise InputError(f"{path}: {where} has no {name}") from None
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{path}: {where} {name} is not a whole number: {value!r}") from None


def _pose(group, path: Path, where: str) -> np.ndarray:
    """A frame's pose in its reference frame from ORIGIN_OFFSET_VECTOR and
    ORIGIN_ROTATION_QUATERNION (s, x, y, z)."""
    return frame_pose(_vector(group, "ORIGIN_OFFSET_VECTOR", 3, path, where),
                      _vector(group, "ORIGIN_ROTATION_QUATERNION", 4, path, where),
                      f"{path}: {where} ORIGIN_ROTATION_QUATERNION")


def _quantity(value) -> float | None:
    if isinstance(value, dict):
        value = value.get("value")
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def read_pds3_label(path: Path) -> RoverImage:
    """One PDS3 label (a detached .LBL or a product with an attached label)."""
    import pdr

    path = Path(path)
    try:
        with warnings.catch_warnings():  # pdr's notes on odd PVL: what is wrong is refused below, by name
            warnings.simplefilter("ignore")
            label = pdr.read(path).metadata
    except Exception as exc:  # noqa: BLE001  pdr raises whatever its parsers meet
        raise InputError(f"{path}: not a readable PDS3 label ({type(exc).__name__}: {exc})") from None
    try:
        start = dt.datetime.fromisoformat(str(_group(label, "START_TIME", path)).rstrip("Z"))
    except ValueError:
        raise InputError(f"{path}: START_TIME {label['START_TIME']!r} is not a UTC time") from None
    counter = _group(label, "ROVER_MOTION_COUNTER", path)
    names = _group(label, "ROVER_MOTION_COUNTER_NAME", path)
    if not isinstance(counter, list | tuple) or not isinstance(names, list | tuple):
        raise InputError(f"{path}: ROVER_MOTION_COUNTER and its _NAME must be lists, got {counter!r} and {names!r}")
    index = {str(name): value for name, value in zip(names, counter, strict=False)}
    if not {"SITE", "DRIVE"} <= index.keys():
        raise InputError(f"{path}: ROVER_MOTION_COUNTER names no SITE and DRIVE: {names}")
    rover = _table(label, "ROVER_COORD_SYSTEM_PARMS", path)
    if rover.get("REFERENCE_COORD_SYSTEM_NAME") != "SITE_FRAME":
        raise InputError(f"{path}: the rover's pose is in {rover.get('REFERENCE_COORD_SYSTEM_NAME')!r}, "
                         "expected SITE_FRAME")
    site_group = _table(label, "SITE_COORD_SYSTEM_PARMS", path, required=False)
    site_origin = None
    if site_group is not None:
        where = "SITE_COORD_SYSTEM_PARMS"
        reference = _integer(site_group, "REFERENCE_COORD_SYSTEM_INDEX", path, where, -1)
        if reference >= 0 and _integer(site_group, "COORDINATE_SYSTEM_INDEX", path, where, reference) != reference:
            site_origin = (reference, _vector(site_group, "ORIGIN_OFFSET_VECTOR", 3, path, "SITE_COORD_SYSTEM_PARMS"))
    model = _table(label, "GEOMETRIC_CAMERA_MODEL_PARMS", path, required=False)
    if model is None:
        raise InputError(f"{path}: no camera model (GEOMETRIC_CAMERA_MODEL_PARMS)")
    kind = str(model.get("MODEL_TYPE", ""))
    parts = {"CAHV": 4, "CAHVOR": 6, "CAHVORE": 7}.get(kind)
    if parts is None:
        raise InputError(f"{path}: camera model type {kind!r}: expected CAHV, CAHVOR or CAHVORE")
    components = [_vector(model, f"MODEL_COMPONENT_{i}", 3, path, "GEOMETRIC_CAMERA_MODEL_PARMS")
                  for i in range(1, parts + 1)]
    if model.get("REFERENCE_COORD_SYSTEM_NAME") not in (None, "ROVER_NAV_FRAME"):
        raise InputError(f"{path}: the camera model is in {model.get('REFERENCE_COORD_SYSTEM_NAME')!r}, expected "
                         "ROVER_NAV_FRAME")
    camera = CameraModel(*components, name=str(path))
    image = _table(label, "IMAGE", path)
    sun = _table(label, "SITE_DERIVED_GEOMETRY_PARMS", path, required=False) or {}
    return RoverImage(
        label=path, utc_s=start.replace(tzinfo=dt.UTC).timestamp(),
        instrument=str(label.get("INSTRUMENT_ID", "")), eye=str(label.get("FRAME_ID", "MONO")),
        site=_integer(index, "SITE", path, "ROVER_MOTION_COUNTER"),
        drive=_integer(index, "DRIVE", path, "ROVER_MOTION_COUNTER"),
        pose=_integer(index, "POSE", path, "ROVER_MOTION_COUNTER", 0),
        site_T_rover=_pose(rover, path, "ROVER_COORD_SYSTEM_PARMS"),
        site_index=_integer(rover, "REFERENCE_COORD_SYSTEM_INDEX", path, "ROVER_COORD_SYSTEM_PARMS", index["SITE"]),
        site_origin=site_origin, camera=camera,
        width=_integer(image, "LINE_SAMPLES", path, "IMAGE"), height=_integer(image, "LINES", path, "IMAGE"),
        sun_site_azimuth_deg=_quantity(sun.get("SOLAR_AZIMUTH")),
        sun_site_elevation_deg=_quantity(sun.get("SOLAR_ELEVATION")),
        mission=str(label.get("INSTRUMENT_HOST_ID", "")), image=image_beside(path))


IMAGE_SUFFIXES = (".IMG", ".img", ".jpg", ".JPG", ".png", ".PNG")


def image_beside(label: Path) -> Path | None:
    """The image of a detached label: the same product name with an image suffix, or the browse
    image archives name with the version character replaced by '_' (NLA_..._M1.LBL and
    NLA_..._M_.jpg)."""
    for stem in (label.stem, label.stem[:-1] + "_"):
        for suffix in IMAGE_SUFFIXES:
            candidate = label.with_name(stem + suffix)
            if candidate.is_file():
                return candidate
    return None


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of a browse image from its header (Pillow reads no pixels); None for a
    PDS .IMG, whose size is its label's."""
    if path.suffix.lower() == ".img":
        return None
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"{path}: not a readable image ({exc})") from None


def read_rover_images(folder: Path) -> list[RoverImage]:
    """Every rover image product under `folder` (PDS3 labels, *.LBL, and PDS4 ones, *.xml whose
    root is a Product_Observational: other XML, such as an MSLICE file, is not a product), in
    time order: one mission's, each image (where there is one beside its label) of the size its
    label gives."""
    folder = Path(folder)
    found = sorted(p for p in folder.rglob("*") if p.suffix in LABEL_SUFFIXES or pds4.is_label(p))
    if not found:
        raise InputError(f"{folder}: no rover image products (PDS3 *.LBL or PDS4 *.xml labels)")
    images = sorted((read_pds3_label(p) if p.suffix in LABEL_SUFFIXES else pds4.read_pds4_label(p) for p in found),
                    key=lambda image: image.utc_s)
    missions: dict[str, Path] = {}
    for image in images:
        missions.setdefault(image.mission, image.label)
        if image.image is not None and image.label.suffix not in LABEL_SUFFIXES:
            pds4.check_image_size(image)
        elif image.image is not None:
            size = image_size(image.image)
            if size is not None and size != (image.width, image.height):
                raise InputError(f"{image.image}: {size[0]} x {size[1]} px, but its label {image.label.name} says "
                                 f"{image.width} x {image.height}")
    if len(missions) > 1:
        raise InputError(f"{folder}: products of more than one mission ("
                         + ", ".join(f"{m or 'no mission named'}: {p.name}" for m, p in missions.items())
                         + "): give one mission's products")
    return images


def site_origins(images: list[RoverImage]) -> dict[int, np.ndarray]:
    """Each site's origin in the first site's frame (north, east, down), chained through the
    offsets the labels give. Site frames are all level and north-aligned, parallel to within
    the distance over Mars' radius (0.02 deg a kilometre)."""
    first = min(image.site_index for image in images)
    links = {image.site_index: image.site_origin for image in images if image.site_origin is not None}
    out = {first: np.zeros(3)}
    for site in sorted({image.site_index for image in images}):
        chain, at = [], site
        while at not in out:
            if at not in links:
                raise InputError(f"{images[0].label.parent}: site {at}'s origin is not given relative to an "
                                 f"earlier site in any label (needed to chain site {site} to site {first})")
            reference, offset = links[at]
            chain.append((at, offset))
            at = reference
        for at_site, offset in reversed(chain):
            out[at_site] = out[links[at_site][0]] + offset
    return out


def enu_T_body(image: RoverImage, origins: dict[int, np.ndarray]) -> np.ndarray:
    """The rover body's pose (x forward, y left, z up) in east-north-up at the first site's
    origin, as the onboard estimate has it."""
    site_T_rover = image.site_T_rover.copy()
    site_T_rover[:3, 3] += origins[image.site_index]
    out = np.eye(4)
    out[:3, :3] = ENU_R_SITE @ site_T_rover[:3, :3] @ BODY_R_ROVER
    out[:3, 3] = ENU_R_SITE @ site_T_rover[:3, 3]
    return out


def site_T_rover(enu_T_body: np.ndarray, site_origin_ned: np.ndarray) -> np.ndarray:
    """`enu_T_body`'s inverse: the rover (forward, right, down) in the site frame (north, east,
    down) whose origin is `site_origin_ned` in the first site's frame."""
    out = np.eye(4)
    out[:3, :3] = ENU_R_SITE @ enu_T_body[:3, :3] @ BODY_R_ROVER
    out[:3, 3] = ENU_R_SITE @ enu_T_body[:3, 3] - site_origin_ned
    return out
