"""Site maps as GeoTIFF (rasterio): an orbital DTM or orthoimage, north-up, in a projected CRS.

What a map must be to be used is checked here, each fault named with its file: a readable
GeoTIFF with one band, a projected CRS (metres), square pixels and no rotation. Heights are
metres above the body's reference surface; the file's nodata becomes NaN."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..records import MapRaster


def write_map_raster(path: Path, raster: MapRaster) -> None:
    """One band: float32 heights with NaN as nodata, or uint8 grey levels."""
    import rasterio
    from rasterio.transform import Affine

    values = raster.values
    dtype = "uint8" if values.dtype == np.uint8 else "float32"
    north_up = Affine(raster.post_m, 0.0, raster.x0_m, 0.0, -raster.post_m, raster.y0_m)
    profile = {"driver": "GTiff", "height": values.shape[0], "width": values.shape[1], "count": 1, "dtype": dtype,
               "crs": raster.crs_wkt, "transform": north_up, "compress": "deflate"}
    if dtype == "float32":
        profile["nodata"] = np.nan
    with rasterio.open(Path(path), "w", **profile) as out:
        out.write(values.astype(dtype), 1)


def read_map_raster(path: Path) -> MapRaster:
    """A map GeoTIFF, checked: one band, a projected CRS, north-up square pixels."""
    import rasterio
    from rasterio.errors import RasterioError

    path = Path(path)
    try:
        found = path.is_file()
    except OSError as exc:  # a name the file system cannot hold (too long)
        raise InputError(f"{path}: not a map file's name ({exc.strerror})") from None
    if not found:
        raise InputError(f"{path}: no such map file")
    try:
        with rasterio.open(path) as source:
            if source.count != 1:
                raise InputError(f"{path}: {source.count} bands; a DTM or a grey orthoimage has one")
            if source.crs is None:
                raise InputError(f"{path}: no CRS: a map must say where it is (a projected CRS in metres)")
            if not source.crs.is_projected:
                raise InputError(f"{path}: CRS {source.crs.to_string()[:60]} is geographic (degrees): expected a "
                                 "projected CRS in metres, e.g. UTM on Earth or equirectangular on Mars")
            t = source.transform
            if t.b != 0.0 or t.d != 0.0:
                raise InputError(f"{path}: rotated pixels (transform {tuple(t)[:6]}): expected a north-up map")
            if t.e >= 0.0 or not np.isclose(t.a, -t.e, rtol=1e-6):
                raise InputError(f"{path}: pixels {t.a} x {-t.e} m: expected square, north-up pixels")
            values = source.read(1)
            nodata = source.nodata
            crs_wkt = source.crs.to_wkt()
    except RasterioError as exc:
        raise InputError(f"{path}: not a readable GeoTIFF ({exc})") from None
    except UnicodeError:  # GDAL hands over a CRS's text that is not UTF-8
        raise InputError(f"{path}: its CRS's text is not UTF-8 (a damaged GeoTIFF)") from None
    if values.dtype == np.uint8:
        if not values.any():
            raise InputError(f"{path}: every grey level is 0 (no data): an orthoimage with nothing to correlate")
        return MapRaster(values, float(t.c), float(t.f), float(t.a), crs_wkt)
    if np.issubdtype(values.dtype, np.integer) and nodata is None:
        raise InputError(f"{path}: {values.dtype} heights with no nodata value: expected float heights in metres "
                         "with NaN (or a stated nodata value) where there are none")
    values = values.astype(np.float32)
    if nodata is not None and not np.isnan(nodata):
        values[values == nodata] = np.nan
    infinite = np.isinf(values)
    if infinite.any():
        row, col = np.argwhere(infinite)[0]
        raise InputError(f"{path}: {int(infinite.sum())} infinite heights (the first at row {row}, column {col}): "
                         "expected finite heights, NaN or the nodata value where there are none")
    if np.isnan(values).all():
        raise InputError(f"{path}: no height at any post (all nodata)")
    return MapRaster(values, float(t.c), float(t.f), float(t.a), crs_wkt)
