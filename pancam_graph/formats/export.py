"""Trajectories for other tools: KITTI poses, and latitude/longitude/height (pyproj back to
WGS84) as CSV, GeoJSON and KML that open in a GIS or Google Earth."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..geometry.geodesy import LocalFrame
from .tables import write_csv

KML_NS = "http://www.opengis.net/kml/2.2"


def write_kitti(path: Path, world_T_body: np.ndarray) -> None:
    """KITTI odometry poses: the first three rows of each 4x4 pose, row-major, one line per pose."""
    np.savetxt(path, np.asarray(world_T_body)[:, :3, :].reshape(-1, 12), fmt="%.9e")


def geodetic(origin: LocalFrame, world_T_body: np.ndarray) -> np.ndarray:
    """(N, 3) latitude deg, longitude deg, ellipsoidal height m of the body positions."""
    return origin.to_geodetic(np.asarray(world_T_body)[:, :3, 3])


def write_geodetic_csv(path: Path, times_s: np.ndarray, lat_lon_h: np.ndarray) -> None:
    write_csv(path, ["time_s", "lat_deg", "lon_deg", "h_ellipsoidal_m"],
              [(f"{t:.6f}", f"{p[0]:.10f}", f"{p[1]:.10f}", f"{p[2]:.4f}") for t, p in zip(times_s, lat_lon_h,
                                                                                      strict=True)])


def write_geojson(path: Path, lat_lon_h: np.ndarray, name: str, times_s: np.ndarray | None = None) -> None:
    """One LineString feature (RFC 7946: longitude, latitude, height; WGS84)."""
    coords = [[round(float(p[1]), 10), round(float(p[0]), 10), round(float(p[2]), 4)] for p in lat_lon_h]
    properties = {"name": name, "height": "ellipsoidal (WGS84), m"}
    if times_s is not None:
        properties["times_s"] = [float(t) for t in times_s]
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": properties, "geometry": {"type": "LineString", "coordinates": coords}}]}
    path.write_text(json.dumps(doc) + "\n", encoding="utf-8")


def write_kml(path: Path, lat_lon_h: np.ndarray, name: str) -> None:
    """A KML LineString; heights are given as 'absolute' (KML's datum is WGS84 height, so
    Google Earth draws it close to, not exactly on, the ground)."""
    ET.register_namespace("", KML_NS)
    kml = ET.Element(f"{{{KML_NS}}}kml")
    placemark = ET.SubElement(ET.SubElement(kml, f"{{{KML_NS}}}Document"), f"{{{KML_NS}}}Placemark")
    ET.SubElement(placemark, f"{{{KML_NS}}}name").text = name
    line = ET.SubElement(placemark, f"{{{KML_NS}}}LineString")
    ET.SubElement(line, f"{{{KML_NS}}}altitudeMode").text = "absolute"
    ET.SubElement(line, f"{{{KML_NS}}}coordinates").text = " ".join(
        f"{p[1]:.10f},{p[0]:.10f},{p[2]:.3f}" for p in lat_lon_h)
    ET.ElementTree(kml).write(path, encoding="utf-8", xml_declaration=True)


def write_trajectory_exports(folder: Path, name: str, origin: LocalFrame | None, times_s: np.ndarray,
                             world_T_body: np.ndarray) -> None:
    """`<name>.kitti`, `<name>_wgs84.csv`, `<name>.geojson` and `<name>.kml` in `folder`. On
    Mars, `<name>_mars_iau2015.csv` (planetocentric latitude, east longitude, height above the
    IAU 2015 sphere) instead of the three, whose formats are WGS84 by definition. Without an
    origin (a frame placed nowhere on a body) the KITTI file only."""
    write_kitti(folder / f"{name}.kitti", world_T_body)
    if origin is None:
        return
    llh = geodetic(origin, world_T_body)
    if origin.body != "earth":
        write_csv(folder / f"{name}_{origin.body}_iau2015.csv", ["time_s", "lat_deg", "lon_deg", "h_m"],
                  [(f"{t:.6f}", f"{p[0]:.10f}", f"{p[1]:.10f}", f"{p[2]:.4f}") for t, p in zip(times_s, llh,
                                                                                          strict=True)])
        return
    write_geodetic_csv(folder / f"{name}_wgs84.csv", times_s, llh)
    write_geojson(folder / f"{name}.geojson", llh, name, times_s)
    write_kml(folder / f"{name}.kml", llh, name)
