"""Feature files in the tile CRS that GIS software reads with that CRS.

RFC 7946 GeoJSON is WGS 84 lon/lat only, so a GeoJSON in a projected CRS is
read by OGR (and QGIS) as lon/lat and lands far off the map. The features in
the tile CRS are therefore written as a GeoPackage, which stores its CRS, and
the native GeoJSON declares its CRS with the (pre-RFC 7946) ``crs`` member
that OGR honours when the CRS has an EPSG code.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import shapely
from shapely.geometry import shape

from terrasift.files import atomic_path


def crs_member(crs_wkt: str | None) -> dict[str, Any] | None:
    """The GeoJSON 2008 ``crs`` member naming the CRS by its EPSG URN (None without an EPSG code)."""
    if not crs_wkt:
        return None
    code = pyproj.CRS.from_user_input(crs_wkt).to_epsg()
    if code is None:
        return None
    return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}"}}


def write_geopackage(
    path: Path, collection: Mapping[str, Any], crs_wkt: str | None, layer: str = "features"
) -> Path:
    """Write a GeoJSON FeatureCollection (native coordinates) as a GeoPackage layer
    in ``crs_wkt`` (none when None), atomically. Properties become columns."""
    from pyogrio.raw import write

    path = Path(path)
    feats = list(collection.get("features", []))
    geoms = [shape(f["geometry"]) for f in feats]
    wkb = np.array([shapely.to_wkb(g) for g in geoms], dtype=object)
    keys: list[str] = []
    for f in feats:
        for k in f.get("properties", {}):
            if k not in keys:
                keys.append(k)
    fields = []
    for k in keys:
        values = [f["properties"].get(k) for f in feats]
        if all(isinstance(v, bool) for v in values if v is not None):
            arr = np.array([bool(v) for v in values])
        elif all(isinstance(v, int) for v in values if v is not None) and None not in values:
            arr = np.array(values, dtype=np.int64)
        elif all(isinstance(v, (int, float)) for v in values if v is not None):
            arr = np.array([np.nan if v is None else float(v) for v in values])
        else:
            arr = np.array(["" if v is None else str(v) for v in values], dtype=object)
        fields.append(arr)
    types = sorted({g.geom_type for g in geoms})
    geometry_type = types[0] if len(types) == 1 else ("Unknown" if types else "Polygon")
    # GDAL wants the .gpkg suffix; without a CRS pyogrio warns (the job's report says so)
    with atomic_path(path, keep_suffix=True) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        write(
            str(tmp),
            geometry=wkb,
            field_data=fields,
            fields=keys,
            crs=crs_wkt or None,
            driver="GPKG",
            layer=layer,
            geometry_type=geometry_type,
        )
    return path
