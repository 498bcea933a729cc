"""Orbital maps that cannot serve the traverse are refused when the run starts, before it writes
anything, naming the map's file: a DTM moved away from its orthoimage, a map that does not cover
the start, a CRS of another body (UTM on Mars), an orthoimage in another CRS than its DTM."""

import shutil

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine
from typer.testing import CliRunner

from pancam_graph.cli import app


@pytest.fixture(scope="module")
def mars_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("maps") / "obs"
    result = CliRunner().invoke(app, ["simulate", "mars_excerpt", "--out", str(folder)])
    assert result.exit_code == 0, result.output
    return folder


def _rewrite(path, change):
    with rasterio.open(path) as src:
        data, profile = src.read(1), src.profile
    data, profile = change(data, dict(profile))
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)


def _moved(data, profile):
    t = profile["transform"]
    profile["transform"] = Affine(t.a, t.b, t.c + 100_000.0, t.d, t.e, t.f)
    return data, profile


def _last_quarter(data, profile):
    t, width = profile["transform"], data.shape[1]
    profile.update(width=width // 4, transform=Affine(t.a, t.b, t.c + 3 * (width // 4) * t.a, t.d, t.e, t.f))
    return data[:, 3 * (width // 4):].copy(), profile


def _utm(data, profile):
    profile["crs"] = rasterio.crs.CRS.from_epsg(32633)
    return data, profile


@pytest.mark.parametrize("raster, change, words", [
    ("dtm", _moved, "its orthoimage and DTM do not overlap"),
    ("dtm", _last_quarter, "does not cover the traverse's start"),
    ("both", _utm, "its CRS is on a body of radius 6,378,137 m, the traverse is on mars"),
    ("orthoimage", _utm, "its orthoimage and DTM are in different CRSs"),
])
def test_a_map_that_cannot_serve_is_refused_naming_its_file_and_nothing_is_left(mars_folder, tmp_path, raster,
                                                                               change, words):
    folder = tmp_path / "obs"
    shutil.copytree(mars_folder, folder)
    for name in ("dtm", "orthoimage") if raster == "both" else (raster,):
        _rewrite(folder / "maps" / f"orbital_map_{name}.tif", change)
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(folder), "--out", str(out), "--configs", "vo_sites_orbital",
                                      "--quiet"])
    assert result.exit_code == 2, result.output
    message = " ".join(result.output.split())
    assert "maps/orbital_map_dtm.tif (orbital map 'orbital_map')" in message and words in message, message
    assert "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obs"]  # no run folder, no .partial


def test_the_untouched_maps_run(mars_folder, tmp_path):
    """The same folder as simulated is not refused (the cases above fail for their change alone)."""
    from pancam_graph.solve.pipeline import select_configurations
    from pancam_graph.sources import open_source

    data = open_source(str(mars_folder))
    chosen, _ = select_configurations(data.estimator, data.traverse, ("vo_sites_orbital",))
    assert list(chosen) == ["vo_sites_orbital"]
    assert np.isfinite(data.traverse.measurements["orbital"][0].dtm.values).any()


def test_a_dtm_in_kilometres_is_named_with_its_offset_from_the_start(mars_folder, tmp_path):
    """Heights in km (or on another datum) pass every check a map can fail alone; its
    registrations then all fail as 'ambiguous'. The run says why first, naming the offset."""
    from pancam_graph.store.observation_folder import read_observations

    folder = tmp_path / "obs"
    shutil.copytree(mars_folder, folder)
    _rewrite(folder / "maps" / "orbital_map_dtm.tif", lambda data, profile: (data / 1000.0, profile))
    notes = [n for n in read_observations(folder).notes if "orbital_map_dtm.tif" in n]
    assert len(notes) == 1 and "apart, against a stated vertical sigma of 1 m" in notes[0], notes
    assert "heights in other units, or on another datum?" in notes[0]
    assert not [n for n in read_observations(mars_folder).notes if "apart" in n]  # the map as simulated: none
