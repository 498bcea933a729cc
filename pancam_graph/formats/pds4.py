"""Rover image products in PDS4 (Mars 2020, ESA's archive): an XML label (Product_Observational)
beside its image (Array_2D_Image, 8-bit, raw). What this project reads and writes of a label is
what a PDS3 label gives (formats/pds.py's RoverImage), in the PDS4 Geometry dictionary's
classes as Mars 2020's labels have them:

    Observation_Area/Time_Coordinates/start_date_time          the image time (UTC)
    Investigation_Area/name                                    the mission
    img_surface:Instrument_Information/instrument_id           the camera and its eye (..._LEFT / _RIGHT)
    geom:Motion_Counter/Motion_Counter_Index                   SITE, DRIVE, POSE
    geom:Camera_Model_Parameters/geom:CAHV[OR[E]]_Model        in ROVER_NAV_FRAME
    geom:Coordinate_Space_Definition ROVER_NAV_FRAME_...       the rover in its SITE_FRAME
    geom:Coordinate_Space_Definition SITE_FRAME_n              the site's origin in site n-1's frame

The labels are written well-formed with these names but not validated against the PDS4 schemas
(PDS's validate tool is Java); pds4_tools reads them (tests/formats/test_pds4.py)."""

from __future__ import annotations

import datetime as dt
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.cahvor import CameraModel
from .rover_image import RoverImage, frame_pose

PDS = "http://pds.nasa.gov/pds4/pds/v1"
GEOM = "http://pds.nasa.gov/pds4/geom/v1"
IMG_SURFACE = "http://pds.nasa.gov/pds4/img_surface/v1"
NAMESPACES = {"pds": PDS, "geom": GEOM, "img_surface": IMG_SURFACE}
LABEL_SUFFIX = ".xml"
EYES = ("LEFT", "RIGHT")

# the model's vectors and the child names of each (Mars 2020's labels)
_VECTORS = (("c", "Vector_Center", ("x_position", "y_position", "z_position")),
            ("a", "Vector_Axis", ("x_unit", "y_unit", "z_unit")),
            ("h", "Vector_Horizontal", ("x_pixel", "y_pixel", "z_pixel")),
            ("v", "Vector_Vertical", ("x_pixel", "y_pixel", "z_pixel")),
            ("o", "Vector_Optical", ("x_unit", "y_unit", "z_unit")))
_TERMS = (("r", "Radial_Terms"), ("e", "Entrance_Terms"))


@dataclass(frozen=True)
class ProductDescription:
    """What a written product's label says (the writer's input)."""

    product_id: str  # names the label (.xml) and the image (.img)
    utc_s: float
    mission: str
    instrument: str  # e.g. WAC_LEFT: the eye is its suffix
    site: int
    drive: int
    pose: int
    site_T_rover: np.ndarray  # 4x4: the rover (x forward, y right, z down) in its site frame (north, east, down)
    site_origin: np.ndarray | None  # this site's origin in the previous site's frame; None for the first site
    camera: CameraModel  # in the rover navigation frame


def _q(namespace: str, tag: str) -> str:
    return f"{{{NAMESPACES[namespace]}}}{tag}"


def _sub(parent: ET.Element, namespace: str, tag: str, text: object = None, **attrs: str) -> ET.Element:
    element = ET.SubElement(parent, _q(namespace, tag), attrs)
    if text is not None:
        element.text = repr(float(text)) if isinstance(text, float | np.floating) else str(text)
    return element


def _indices(parent: ET.Element, tag: str, values: dict[str, int]) -> None:
    for name, value in values.items():
        index = _sub(parent, "geom", tag)
        _sub(index, "geom", "index_id", name)
        _sub(index, "geom", "index_value_number", value)


def _frame_definition(geometry: ET.Element, identifier: str, frame_type: str, indices: dict[str, int],
                      pose: np.ndarray, reference: str) -> None:
    """A geom:Coordinate_Space_Definition: the frame's origin and rotation in its reference."""
    from scipy.spatial.transform import Rotation

    definition = _sub(geometry, "geom", "Coordinate_Space_Definition")
    _sub(definition, "pds", "local_identifier", identifier)
    indexed = _sub(_sub(definition, "geom", "Coordinate_Space_Present"), "geom", "Coordinate_Space_Indexed")
    _sub(indexed, "geom", "coordinate_space_frame_type", frame_type)
    _indices(indexed, "Coordinate_Space_Index", indices)
    offset = _sub(definition, "geom", "Vector_Origin_Offset")
    for name, value in zip(("x_position", "y_position", "z_position"), pose[:3, 3], strict=True):
        _sub(offset, "geom", name, float(value), unit="m")
    x, y, z, s = Rotation.from_matrix(pose[:3, :3]).as_quat()
    quaternion = _sub(definition, "geom", "Quaternion_Plus_Direction")
    for name, value in zip(("qcos", "qsin1", "qsin2", "qsin3"), (s, x, y, z), strict=True):
        _sub(quaternion, "geom", name, float(value))
    _sub(quaternion, "geom", "rotation_direction", "Forward")
    local = _sub(_sub(definition, "geom", "Coordinate_Space_Reference"), "pds", "Local_Internal_Reference")
    _sub(local, "pds", "local_identifier_reference", reference)
    _sub(local, "pds", "local_reference_type", "to_reference_coordinate_space")


def write_product(folder: Path, product: ProductDescription, image: np.ndarray) -> Path:
    """The product's label and its raw 8-bit image in `folder`; returns the label's path."""
    for prefix, uri in NAMESPACES.items():
        ET.register_namespace("" if prefix == "pds" else prefix, uri)
    image = np.ascontiguousarray(image, dtype=np.uint8)
    lines, samples = image.shape
    folder = Path(folder)
    data_name = product.product_id + ".img"
    (folder / data_name).write_bytes(image.tobytes())

    root = ET.Element(_q("pds", "Product_Observational"))
    ident = _sub(root, "pds", "Identification_Area")
    _sub(ident, "pds", "logical_identifier", f"urn:nasa:pds:pancam_graph:data:{product.product_id.lower()}")
    _sub(ident, "pds", "version_id", "1.0")
    _sub(ident, "pds", "title", f"{product.instrument} image, site {product.site} drive {product.drive}")
    _sub(ident, "pds", "product_class", "Product_Observational")
    observation = _sub(root, "pds", "Observation_Area")
    times = _sub(observation, "pds", "Time_Coordinates")
    start = dt.datetime.fromtimestamp(product.utc_s, dt.UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")
    _sub(times, "pds", "start_date_time", start)
    _sub(times, "pds", "stop_date_time", start)
    investigation = _sub(observation, "pds", "Investigation_Area")
    _sub(investigation, "pds", "name", product.mission)
    _sub(investigation, "pds", "type", "Mission")
    discipline = _sub(observation, "pds", "Discipline_Area")
    info = _sub(_sub(discipline, "img_surface", "Surface_Imaging"), "img_surface", "Instrument_Information")
    _sub(info, "img_surface", "instrument_id", product.instrument)
    geometry = _sub(_sub(discipline, "geom", "Geometry"), "geom", "Geometry_Lander")
    counter = _sub(geometry, "geom", "Motion_Counter")
    _indices(counter, "Motion_Counter_Index", {"SITE": product.site, "DRIVE": product.drive, "POSE": product.pose})
    parameters = _sub(geometry, "geom", "Camera_Model_Parameters")
    camera = product.camera
    _sub(parameters, "geom", "model_type", camera.kind)
    model = _sub(parameters, "geom", f"{camera.kind}_Model")
    for key, tag, names in _VECTORS:
        value = getattr(camera, key)
        if value is not None:
            vector = _sub(model, "geom", tag)
            for name, component in zip(names, value, strict=True):
                _sub(vector, "geom", name, float(component))
    for key, tag in _TERMS:
        value = getattr(camera, key)
        if value is not None:
            terms = _sub(model, "geom", tag)
            for i, term in enumerate(value):
                _sub(terms, "geom", f"c{i}", float(term))
    counters = {"SITE": product.site, "DRIVE": product.drive, "POSE": product.pose}
    indexed = _sub(_sub(parameters, "geom", "Coordinate_Space_Reference"), "geom", "Coordinate_Space_Indexed")
    _sub(indexed, "geom", "coordinate_space_frame_type", "ROVER_NAV_FRAME")
    _indices(indexed, "Coordinate_Space_Index", counters)
    site_frame = f"SITE_FRAME_{product.site}"
    _frame_definition(geometry, f"ROVER_NAV_FRAME_{product.site}_{product.drive}_{product.pose}", "ROVER_NAV_FRAME",
                      counters, product.site_T_rover, site_frame)
    if product.site_origin is not None:
        origin = np.eye(4)
        origin[:3, 3] = product.site_origin
        _frame_definition(geometry, site_frame, "SITE_FRAME", {"SITE": product.site}, origin,
                          f"SITE_FRAME_{product.site - 1}")

    files = _sub(root, "pds", "File_Area_Observational")
    _sub(_sub(files, "pds", "File"), "pds", "file_name", data_name)
    array = _sub(files, "pds", "Array_2D_Image")
    _sub(array, "pds", "local_identifier", "image")
    _sub(array, "pds", "offset", 0, unit="byte")
    _sub(array, "pds", "axes", 2)
    _sub(array, "pds", "axis_index_order", "Last Index Fastest")
    _sub(_sub(array, "pds", "Element_Array"), "pds", "data_type", "UnsignedByte")
    for name, size, sequence in (("Line", lines, 1), ("Sample", samples, 2)):
        axis = _sub(array, "pds", "Axis_Array")
        _sub(axis, "pds", "axis_name", name)
        _sub(axis, "pds", "elements", size)
        _sub(axis, "pds", "sequence_number", sequence)
    ET.indent(root)
    path = folder / (product.product_id + LABEL_SUFFIX)
    ET.ElementTree(root).write(path, encoding="UTF-8", xml_declaration=True)
    return path


# -- reading ---------------------------------------------------------------------------------


class _Label:
    """A parsed label and its path, for finding elements and naming what is missing."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.root = ET.parse(path).getroot()
        except (ET.ParseError, OSError, ValueError, LookupError) as exc:  # LookupError: an unknown encoding
            raise InputError(f"{path}: not a readable PDS4 label ({exc})") from None
        if self.root.tag != _q("pds", "Product_Observational"):
            raise InputError(f"{path}: a {self.root.tag.rpartition('}')[2]}, expected a Product_Observational")

    def find(self, at: ET.Element, where: str, required: bool = True) -> ET.Element | None:
        found = at.find(where, NAMESPACES)
        if found is None and required:
            raise InputError(f"{self.path}: no {where.replace('./', '')} in the label")
        return found

    def text(self, at: ET.Element, where: str) -> str:
        return (self.find(at, where).text or "").strip()

    def number(self, at: ET.Element, where: str) -> float:
        text = self.text(at, where)
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"{self.path}: {where} is {text!r}, expected a number") from None
        if not np.isfinite(value):
            raise InputError(f"{self.path}: {where} is {text!r}, expected a finite number")
        return value

    def whole(self, at: ET.Element, where: str) -> int:
        text = self.text(at, where)
        try:
            return int(text)
        except ValueError:
            raise InputError(f"{self.path}: {where} is {text!r}, expected a whole number") from None

    def indices(self, at: ET.Element, tag: str) -> dict[str, int]:
        return {self.text(i, "geom:index_id"): self.whole(i, "geom:index_value_number")
                for i in at.findall(f"geom:{tag}", NAMESPACES)}

    def vector(self, at: ET.Element, names: tuple[str, ...]) -> np.ndarray:
        return np.array([self.number(at, f"geom:{name}") for name in names])

    def definition(self, geometry: ET.Element, identifier: str) -> ET.Element | None:
        for definition in geometry.findall("geom:Coordinate_Space_Definition", NAMESPACES):
            if identifier in [e.text for e in definition.findall("pds:local_identifier", NAMESPACES)]:
                return definition
        return None

    def pose(self, definition: ET.Element, identifier: str) -> np.ndarray:
        offset = self.vector(self.find(definition, "geom:Vector_Origin_Offset"),
                             ("x_position", "y_position", "z_position"))
        quaternion = self.find(definition, "geom:Quaternion_Plus_Direction")
        s_x_y_z = tuple(self.number(quaternion, f"geom:{n}") for n in ("qcos", "qsin1", "qsin2", "qsin3"))
        return frame_pose(offset, s_x_y_z, f"{self.path}: {identifier}'s quaternion")


def _camera(label: _Label, geometry: ET.Element) -> CameraModel:
    parameters = label.find(geometry, "geom:Camera_Model_Parameters", required=False)
    if parameters is None:
        raise InputError(f"{label.path}: no camera model (geom:Camera_Model_Parameters)")
    kind = label.text(parameters, "geom:model_type")
    if kind not in ("CAHV", "CAHVOR", "CAHVORE"):
        raise InputError(f"{label.path}: camera model type {kind!r}: expected CAHV, CAHVOR or CAHVORE")
    frame = label.find(parameters, "./geom:Coordinate_Space_Reference/geom:Coordinate_Space_Indexed/"
                                   "geom:coordinate_space_frame_type", required=False)
    if frame is not None and frame.text != "ROVER_NAV_FRAME":
        raise InputError(f"{label.path}: the camera model is in {frame.text!r}, expected ROVER_NAV_FRAME")
    model = label.find(parameters, f"geom:{kind}_Model")
    parts = {"CAHV": 4, "CAHVOR": 5, "CAHVORE": 5}[kind]
    values = {key: label.vector(label.find(model, f"geom:{tag}"), names) for key, tag, names in _VECTORS[:parts]}
    for key, tag in _TERMS[:{"CAHV": 0, "CAHVOR": 1, "CAHVORE": 2}[kind]]:
        values[key] = label.vector(label.find(model, f"geom:{tag}"), ("c0", "c1", "c2"))
    return CameraModel(**values, name=str(label.path))


def read_pds4_label(path: Path) -> RoverImage:
    """One PDS4 rover image product's label."""
    path = Path(path)
    label = _Label(path)
    root = label.root
    start = label.text(root, "./pds:Observation_Area/pds:Time_Coordinates/pds:start_date_time")
    try:
        utc = dt.datetime.fromisoformat(start.rstrip("Z")).replace(tzinfo=dt.UTC)
    except ValueError:
        raise InputError(f"{path}: start_date_time {start!r} is not a UTC time") from None
    discipline = label.find(root, "./pds:Observation_Area/pds:Discipline_Area")
    instrument = label.text(discipline, ".//img_surface:Instrument_Information/img_surface:instrument_id")
    geometry = label.find(discipline, "./geom:Geometry/geom:Geometry_Lander")
    counter = label.indices(label.find(geometry, "geom:Motion_Counter"), "Motion_Counter_Index")
    if not {"SITE", "DRIVE"} <= counter.keys():
        raise InputError(f"{path}: geom:Motion_Counter names no SITE and DRIVE: {sorted(counter)}")
    site, drive, pose = counter["SITE"], counter["DRIVE"], counter.get("POSE", 0)
    rover_id = f"ROVER_NAV_FRAME_{site}_{drive}_{pose}"
    rover = label.definition(geometry, rover_id)
    if rover is None:
        raise InputError(f"{path}: no geom:Coordinate_Space_Definition {rover_id} (the rover's pose in its site "
                         "frame)")
    reference = label.text(rover, "./geom:Coordinate_Space_Reference/pds:Local_Internal_Reference/"
                                  "pds:local_identifier_reference")
    site_frame = re.fullmatch(r"SITE_FRAME_(\d+)", reference, re.ASCII)
    if site_frame is None:
        raise InputError(f"{path}: the rover's pose is in {reference!r}, expected a SITE_FRAME_<site>")
    site_origin = None
    site_definition = label.definition(geometry, f"SITE_FRAME_{site}")
    if site_definition is not None:
        previous = label.text(site_definition, "./geom:Coordinate_Space_Reference/pds:Local_Internal_Reference/"
                                               "pds:local_identifier_reference")
        try:
            site_origin = (int(previous.removeprefix("SITE_FRAME_")),
                           label.pose(site_definition, f"SITE_FRAME_{site}")[:3, 3])
        except ValueError:
            raise InputError(f"{path}: SITE_FRAME_{site} is given in {previous!r}, expected a SITE_FRAME") from None
    array = label.find(root, "./pds:File_Area_Observational/pds:Array_2D_Image")
    data_type = label.text(array, "./pds:Element_Array/pds:data_type")
    if data_type != "UnsignedByte":
        raise InputError(f"{path}: the image's data_type is {data_type!r}: only 8-bit images (UnsignedByte) are read")
    sizes = {label.text(a, "pds:axis_name"): label.whole(a, "pds:elements")
             for a in array.findall("pds:Axis_Array", NAMESPACES)}
    if set(sizes) != {"Line", "Sample"}:
        raise InputError(f"{path}: the image's axes are {sorted(sizes)}, expected Line and Sample")
    file_name = label.text(root, "./pds:File_Area_Observational/pds:File/pds:file_name")
    image = path.parent / file_name
    try:
        found = image.is_file()
    except (OSError, ValueError):  # a name too long for the file system, or with a NUL
        raise InputError(f"{path}: file_name {file_name[:60]!r}{'...' if len(file_name) > 60 else ''} is not a "
                         "file name this system can open") from None
    eye = instrument.rpartition("_")[2] if instrument.rpartition("_")[2] in EYES else "MONO"
    return RoverImage(
        label=path, utc_s=utc.timestamp(), instrument=instrument, eye=eye, site=site, drive=drive, pose=pose,
        site_T_rover=label.pose(rover, rover_id), site_index=int(site_frame.group(1)),
        site_origin=site_origin, camera=_camera(label, geometry), width=sizes["Sample"], height=sizes["Line"],
        sun_site_azimuth_deg=None, sun_site_elevation_deg=None,
        mission=label.text(root, "./pds:Observation_Area/pds:Investigation_Area/pds:name"),
        image=image if found else None)


def read_image(image: RoverImage) -> np.ndarray:
    """A PDS4 product's 8-bit image (lines x samples), checked against its label's size."""
    if image.image is None:
        raise InputError(f"{image.label}: its image file is missing")
    data = np.fromfile(image.image, dtype=np.uint8)
    if data.size != image.width * image.height:
        raise InputError(f"{image.image}: {data.size} bytes, but its label {image.label.name} says "
                         f"{image.width} x {image.height} 8-bit pixels")
    return data.reshape(image.height, image.width)


def is_label(path: Path) -> bool:
    """An .xml file whose root element is a PDS4 Product_Observational (read up to its first tag)."""
    if path.suffix != LABEL_SUFFIX or not path.is_file():
        return False
    try:
        for _, element in ET.iterparse(path, events=("start",)):
            return element.tag == _q("pds", "Product_Observational")
    except (ET.ParseError, OSError, ValueError, LookupError):
        return False
    return False


def check_image_size(image: RoverImage) -> None:
    """A product's raw 8-bit image holds the label's width x height bytes, or InputError naming it."""
    size = image.image.stat().st_size
    if size != image.width * image.height:
        raise InputError(f"{image.image}: {size} bytes, but its label {image.label.name} says {image.width} x "
                         f"{image.height} 8-bit pixels")
