"""MSLICE's ground-updated rover locations (the MSL science operations tool's `<msl><location>`
XML): per site and drive, the planetocentric latitude and east longitude the operations team
placed the rover at on the orbital base map. A reference made on the ground, after the drive:
a rover's onboard positions are compared with it, never fed from it."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from ..errors import InputError

FILE_PATTERN = "mslice_locations*.xml"


@dataclass(frozen=True)
class MsliceLocation:
    site: int
    drive: int
    lat_deg: float  # planetocentric
    lon_deg: float  # east
    arrival_utc_s: float | None  # when the rover reached it (POSIX seconds), when given


def read_mslice_locations(path: Path) -> dict[tuple[int, int], MsliceLocation]:
    """Every location of an MSLICE file by (site, drive)."""
    path = Path(path)
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError) as exc:
        raise InputError(f"{path}: not a readable MSLICE locations file ({exc})") from None
    out: dict[tuple[int, int], MsliceLocation] = {}
    for number, location in enumerate(root.iter("location"), start=1):
        fields = {child.tag: (child.text or "").strip() for child in location}
        where = f"{path}: location {number}"
        try:
            site, drive = int(fields["site"]), int(fields["drive"])
            lat, lon = float(fields["lat"]), float(fields["lon"])
        except KeyError as exc:
            raise InputError(f"{where} has no <{exc.args[0]}>") from None
        except ValueError:
            raise InputError(f"{where}: site, drive, lat or lon is not a number: {fields}") from None
        if not (np.isfinite(lat) and -90.0 <= lat <= 90.0 and np.isfinite(lon) and -180.0 <= lon <= 360.0):
            raise InputError(f"{where}: lat {lat:g}, lon {lon:g} is not a place (expected -90..90, -180..360 deg)")
        arrival = None
        if fields.get("arrivalTime"):
            try:
                arrival = dt.datetime.fromisoformat(fields["arrivalTime"].rstrip("Z")).replace(
                    tzinfo=dt.UTC).timestamp()
            except ValueError:
                raise InputError(f"{where}: arrivalTime {fields['arrivalTime']!r} is not a UTC time") from None
        out[(site, drive)] = MsliceLocation(site, drive, lat, lon, arrival)
    if not out:
        raise InputError(f"{path}: no <location> in it (an MSLICE locations file lists <msl><location>...)")
    return out


def find_mslice_file(folder: Path) -> Path | None:
    """The MSLICE locations file in a folder of products, if there is exactly one."""
    found = sorted(Path(folder).glob(FILE_PATTERN))
    if len(found) > 1:
        raise InputError(f"{folder}: {len(found)} MSLICE files ({', '.join(p.name for p in found)}): keep one")
    return found[0] if found else None


def write_mslice_locations(path: Path, locations: list[MsliceLocation]) -> None:
    """An MSLICE-style locations file (the fields this module reads, zero-padded as MSLICE has them)."""
    root = ElementTree.Element("msl")
    for location in locations:
        element = ElementTree.SubElement(root, "location")
        for tag, text in (("site", f"{location.site:05d}"), ("drive", f"{location.drive:05d}"),
                          ("lat", repr(float(location.lat_deg))), ("lon", repr(float(location.lon_deg)))):
            ElementTree.SubElement(element, tag).text = text
        if location.arrival_utc_s is not None:
            arrival = dt.datetime.fromtimestamp(location.arrival_utc_s, dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
            ElementTree.SubElement(element, "arrivalTime").text = arrival
    ElementTree.indent(root)
    ElementTree.ElementTree(root).write(path, encoding="UTF-8", xml_declaration=True)
