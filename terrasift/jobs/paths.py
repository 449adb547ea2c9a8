"""Pitch and roll along a path over a finished job's DTM (NIST §5.3)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from terrasift.files import load_json
from terrasift.jobs.dirs import output_path
from terrasift.jobs.plan import _crs_label
from terrasift.workers.terrain import Smooth


def job_path_profile(
    job_dir: Path,
    geometry: Mapping[str, Any],
    *,
    crs: str | None = None,
    spacing: float | None = None,
) -> Any:
    """Pitch and roll along a GeoJSON LineString over a finished job's DTM (see ``dtm_path_profile``)."""
    from terrasift.jobs.params import stage_params

    params = load_json(Path(job_dir) / "job.json")["params"]
    tparams = stage_params(params, "terrain")
    return dtm_path_profile(
        output_path(job_dir, "dtm.tif"),
        geometry,
        crs=crs,
        spacing=spacing or tparams.spacing,
        median_size=tparams.median_size,
        smooth=tparams.smooth,
    )


def dtm_path_profile(
    dtm_path: Path,
    geometry: Mapping[str, Any],
    *,
    crs: str | None = None,
    spacing: float = 1.0,
    median_size: int = 3,
    smooth: Smooth = "gradient",
) -> Any:
    """Pitch and roll along GeoJSON lines (a LineString, a Feature or a
    FeatureCollection of them) over a DTM GeoTIFF; x, y of the samples are in
    the DTM's CRS, which the result names.

    ``crs`` names the lines' CRS: None for the GeoJSON's ``crs`` member or else
    WGS 84 lon/lat (RFC 7946), ``"native"`` for the DTM's CRS, or any CRS
    string. Raises ParameterError for a bad line.
    """
    import rasterio

    from terrasift.errors import ParameterError
    from terrasift.workers import terrain

    if not 0 < spacing <= 10_000:
        raise ParameterError("spacing must be in (0, 10000] metres")
    with rasterio.open(dtm_path) as ds:
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        transform = ds.transform
        tile_crs = ds.crs.to_wkt() if ds.crs else None
    lines, member_crs = terrain.path_lines(dict(geometry))
    crs = crs or member_crs  # a crs member (QGIS exports one) names the line's CRS
    if crs is not None and crs != "native" and tile_crs is not None:
        try:
            if pyproj.CRS.from_user_input(crs).equals(pyproj.CRS.from_wkt(tile_crs)):
                crs = "native"
        except pyproj.exceptions.CRSError:
            raise ParameterError(f"unknown CRS {crs!r}") from None
    profiles = []
    for g in lines:
        if crs == "native" or (crs is None and tile_crs is None):
            line = terrain.line_coordinates(g, None)
        else:
            if tile_crs is None:
                raise ParameterError(
                    "the DTM has no CRS: give the line in its coordinates (crs=native)"
                )
            line = terrain.line_coordinates(g, tile_crs, crs or "EPSG:4326")
        length = float(np.sum(np.hypot(*np.diff(line, axis=0).T)))
        if length / spacing > 1_000_000:
            raise ParameterError(
                f"a {length:.0f} m path at {spacing} m spacing is over a million samples"
            )
        profiles.append(terrain.path_profile(dtm, transform, line, spacing, median_size, smooth))
    return terrain.PathProfiles(profiles, _crs_label(tile_crs))
