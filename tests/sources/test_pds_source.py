"""The PDS source (sources/pds.py) on the real Curiosity Navcam products of sols 26-57: one stop a
drive, the onboard kind's estimate of them, scored against MSLICE's ground-updated positions.
The reference side is computed here on its own (ElementTree for MSLICE, a sphere's local
east-north for the positions), never through the library's frames."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from mars_reference import mslice_locations

from pancam_graph import api
from pancam_graph.errors import InputError
from pancam_graph.formats.pds import enu_T_body, read_rover_images, site_origins
from pancam_graph.sources import source_for
from pancam_graph.sources.pds import load, stops_of

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
CURIOSITY = REAL / "curiosity_navcam_sol26_57"
MARS_RADIUS_M = 3396190.0  # IAU 2015 sphere, as MSLICE and the maps have it
pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(not CURIOSITY.is_dir(), reason=f"needs {CURIOSITY} (../shared beside the checkout)")]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pds") / "run"
    return api.run(str(CURIOSITY), out=out, figures=False, processes=1)


@pytest.fixture(scope="module")
def groups():
    return stops_of(read_rover_images(CURIOSITY))


def _mslice_east_north(groups) -> np.ndarray:
    mslice = mslice_locations(CURIOSITY / "mslice_locations_sol0_59.xml")
    lat0, lon0 = mslice[(3, 0)]
    lat, lon = np.array([mslice[(g[0].site, g[0].drive)] for g in groups]).T
    return np.column_stack([MARS_RADIUS_M * np.cos(np.radians(lat0)) * np.radians(lon - lon0),
                            MARS_RADIUS_M * np.radians(lat - lat0)])


def _similarity(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Umeyama's rotation (deg, anticlockwise) and scale taking 2-D points a onto b."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    u, s, vt = np.linalg.svd(cb.T @ ca / len(a))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return np.degrees(np.arctan2(rotation[1, 0], rotation[0, 0])), np.trace(np.diag(s) @ d) / np.mean(
        np.sum(ca**2, axis=1))


def test_the_folder_is_read_as_pds_products_with_one_stop_a_drive(groups):
    assert source_for(str(CURIOSITY)).name == "pds"
    data = load(CURIOSITY)
    assert len(data.traverse.stops) == len(groups) == 110
    assert [s.time_s for s in data.traverse.stops] == sorted(s.time_s for s in data.traverse.stops)
    assert sum("left images only" in note for note in data.info.notes) == 1
    assert data.info.georeferenced and data.traverse.origin.body == "mars"


def test_the_onboard_estimate_keeps_the_onboard_chain(run, groups):
    origins = site_origins([image for group in groups for image in group])
    chain = np.array([enu_T_body(g[0], origins)[:3, 3] for g in groups])
    estimate = run.result.configurations["onboard"].world_T_body[:, :3, 3]
    # the onboard tilts pull the chain by at most a few centimetres over 330 m
    assert np.abs(estimate - chain).max() < 0.05


def test_it_is_scored_against_mslice_at_every_drive(run, groups):
    estimate = run.result.configurations["onboard"].world_T_body[:, :2, 3]
    reference = _mslice_east_north(groups)
    rms = np.sqrt(np.mean(np.sum((estimate - reference) ** 2, axis=1)))
    metrics = json.loads(run.metrics_path.read_text())["configs"]["onboard"]["vs_held_out_gps"]
    assert metrics["held_out_fixes"] == 110
    assert metrics["rms_2d_m"] == pytest.approx(rms, abs=0.01)
    assert 4.0 < rms < 5.5  # site 4's origin alone was moved 3.3 m by the ground update
    # the run's own similarity fit (evaluation.metrics.fit_similarity_2d, in the library's frame) against
    # the one here on a sphere's local east-north: 0.434 deg and -0.489 %, the frames 0.0003 deg apart
    rotation_all, scale_all = _similarity(estimate, reference)
    assert metrics["rotation_deg"] == pytest.approx(rotation_all, abs=2e-3)
    assert metrics["scale_pct"] == pytest.approx((scale_all - 1.0) * 100, abs=2e-3)
    assert metrics["rms_2d_after_similarity_m"] < rms / 3
    on_site_4 = np.array([g[0].site == 4 for g in groups])
    rotation_deg, scale = _similarity(estimate[on_site_4], reference[on_site_4])
    # the data's README: over site 4 MSLICE is the onboard track turned 0.27 deg and shrunk 0.27 %
    assert rotation_deg == pytest.approx(0.27, abs=0.02)
    assert (scale - 1.0) * 100 == pytest.approx(-0.27, abs=0.02)


def test_the_frame_is_placed_on_mars_at_mslice_s_first_site(run):
    mslice = mslice_locations(CURIOSITY / "mslice_locations_sol0_59.xml")
    frame = json.loads((run.folder / "local_frame.json").read_text())
    assert (frame["lat_deg"], frame["lon_deg"]) == pytest.approx(mslice[(3, 0)], abs=1e-12)


def _copy_labels(tmp_path: Path, sols: list[str], mslice: bool) -> Path:
    folder = tmp_path / "products"
    for sol in sols:
        (folder / sol).mkdir(parents=True)
        for label in (CURIOSITY / sol).glob("*.LBL"):
            shutil.copy(label, folder / sol)
    if mslice:
        shutil.copy(CURIOSITY / "mslice_locations_sol0_59.xml", folder)
    return folder


def test_without_mslice_the_frame_is_not_placed_and_it_says_so(tmp_path):
    data = load(_copy_labels(tmp_path, ["sol0026"], mslice=False))
    assert not data.info.georeferenced and not data.held_out
    assert any("no MSLICE locations file" in note for note in data.info.notes)


def test_products_of_one_stop_are_refused_naming_the_folder(tmp_path):
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copy(CURIOSITY / "sol0026" / "NLA_399801979EDR_D0030382TRAV00006M1.LBL", folder)
    with pytest.raises(InputError, match="one stop only"):
        load(folder)


def test_a_broken_mslice_file_is_named(tmp_path):
    folder = _copy_labels(tmp_path, ["sol0026"], mslice=False)
    (folder / "mslice_locations_x.xml").write_text("<msl><location><site>3</site></location></msl>")
    with pytest.raises(InputError, match=r"mslice_locations_x.xml: location 1 has no <drive>"):
        load(folder)


def test_the_localization_product_opens_in_iau_2015_with_the_labels_motion_counter_and_attitude(run, groups):
    """The GeoPackage read back with pyogrio: 110 stops in the IAU 2015 Mars sphere's CRS, each with
    its label's site and drive, and its roll, pitch and yaw those of the label's onboard
    quaternion (site frame north-east-down, rover forward-right-down), within the tilt factors' pull."""
    import pyogrio
    from pyproj import CRS
    from scipy.spatial.transform import Rotation

    meta, _, _, fields = pyogrio.raw.read(run.folder / "localization_onboard.gpkg", layer="stops")
    assert CRS.from_user_input(meta["crs"]).equals(CRS.from_user_input("IAU_2015:49900"))
    column = dict(zip(meta["fields"], fields, strict=True))
    assert len(column["stop"]) == 110
    assert [(s, d) for s, d in zip(column["site"], column["drive"], strict=True)] == [
        (g[0].site, g[0].drive) for g in groups]
    yaw, pitch, roll = np.degrees(np.array([Rotation.from_matrix(g[0].site_T_rover[:3, :3]).as_euler("ZYX")
                                            for g in groups]).T)
    # measured: 0.0007 deg in yaw, 0.007 in pitch and roll
    assert np.abs((column["yaw"] - yaw % 360 + 180) % 360 - 180).max() < 0.02
    assert np.abs(column["pitch"] - pitch).max() < 0.02 and np.abs(column["roll"] - roll).max() < 0.02
