"""The STAC Item of a job's outputs, described from the files themselves.

Every raster asset carries its own grid (``proj:shape``, ``proj:transform``)
and bands (``raster:bands``: nodata, data type, unit), read from the GeoTIFF,
so an Item never claims the DTM's grid for a 1 m coverage or a 2 m category
raster. A classified point cloud asset carries the pointcloud extension
(count, type, encoding, dimensions) from its LAS header. The footprint is the
outline of the DTM's valid cells (not the bounding box), in WGS 84. Without a
CRS the Item has ``geometry: null`` and no ``bbox``, as the spec allows.

``datetime`` is when the data was taken, as far as the LAS headers tell (their
creation date, day of year); the processing time is ``created``. Headers
without a date leave ``datetime`` null with ``start_datetime``/``end_datetime``
bounding it by the input files' modification times.
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

STAC_VERSION = "1.1.0"
PROJECTION = "https://stac-extensions.github.io/projection/v2.0.0/schema.json"
RASTER = "https://stac-extensions.github.io/raster/v1.1.0/schema.json"
POINTCLOUD = "https://stac-extensions.github.io/pointcloud/v2.0.0/schema.json"

MEDIA_TYPES = {
    ".tif": "image/tiff; application=geotiff; profile=cloud-optimized",
    ".laz": "application/vnd.laszip",
    ".las": "application/vnd.las",
    ".geojson": "application/geo+json",
    ".gpkg": "application/geopackage+sqlite3",
    ".json": "application/json",
    ".png": "image/png",
}

#: asset roles beyond "data"
ROLES = {
    "report.json": ["metadata"],
    "steep_blocks.geojson": ["metadata"],
}


def _default_role(name: str, suffix: str) -> list[str]:
    if suffix == ".json":
        return ["metadata"]
    if suffix == ".png":  # quicklooks
        return ["thumbnail"] if name == "thumbnail.png" else ["overview"]
    return ["data"]


def _iso(t: dt.datetime) -> str:
    return t.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


def raster_asset(path: Path) -> dict[str, Any]:
    """Projection and raster extension fields of one GeoTIFF, from the file."""
    import rasterio

    with rasterio.open(path) as ds:
        t = ds.transform
        bands = []
        for i in range(1, ds.count + 1):
            band: dict[str, Any] = {"data_type": ds.dtypes[i - 1]}
            nodata = ds.nodatavals[i - 1]
            if nodata is not None:
                band["nodata"] = _nodata(nodata)
            unit = ds.units[i - 1] if ds.units else None
            if unit:
                band["unit"] = unit
            desc = ds.descriptions[i - 1] if ds.descriptions else None
            if desc:
                band["name"] = desc
            band["spatial_resolution"] = float(abs(t.a))
            bands.append(band)
        return {
            "proj:shape": [ds.height, ds.width],
            "proj:transform": [t.a, t.b, t.c, t.d, t.e, t.f],
            "raster:bands": bands,
        }


def _nodata(v: float) -> float | int | str:
    if np.isnan(v):
        return "nan"
    if np.isinf(v):
        return "inf" if v > 0 else "-inf"
    return int(v) if float(v).is_integer() else float(v)


def pointcloud_asset(path: Path) -> dict[str, Any]:
    """Pointcloud extension fields of one LAS/LAZ file, from its header."""
    import laspy

    with laspy.open(path) as reader:
        h = reader.header
        schemas = []
        for dim in h.point_format.dimensions:
            kind = dim.kind.name
            typ = {"FloatingPoint": "floating", "SignedInteger": "signed"}.get(kind, "unsigned")
            # bit fields take whole bytes in the schema (the smallest size it can state)
            size = max(1, -(-int(dim.num_bits) // 8)) * max(1, int(dim.num_elements or 1))
            schemas.append({"name": dim.name, "size": size, "type": typ})
        area = float(np.prod(np.maximum(np.asarray(h.maxs[:2]) - np.asarray(h.mins[:2]), 1e-9)))
        return {
            "pc:count": int(h.point_count),
            "pc:type": "lidar",
            "pc:encoding": "LASzip" if path.suffix.lower() == ".laz" else "LAS",
            "pc:schemas": schemas,
            "pc:density": float(h.point_count / area),
        }


def acquisition_dates(inputs: list[str]) -> tuple[dt.datetime | None, dt.datetime | None, bool]:
    """(first, last) date of the inputs and whether it came from the LAS headers."""
    import laspy

    dates = []
    for p in inputs:
        try:
            with laspy.open(p) as r:
                d = r.header.creation_date
        except Exception:
            d = None
        if d is not None:
            dates.append(dt.datetime(d.year, d.month, d.day, tzinfo=dt.UTC))
    if dates:
        return min(dates), max(dates), True
    times = [
        dt.datetime.fromtimestamp(os.stat(p).st_mtime, dt.UTC) for p in inputs if Path(p).exists()
    ]
    if not times:
        return None, None, False
    return min(times), max(times), False


def footprint(dtm_path: Path, crs_wkt: str, max_cells: int = 512) -> dict[str, Any] | None:
    """Outline of the DTM's valid cells (at most ``max_cells`` across), as a
    WGS 84 GeoJSON geometry; None when the DTM has no valid cell."""
    import pyproj
    import rasterio
    import shapely
    from rasterio import features
    from shapely.geometry import mapping, shape
    from shapely.ops import unary_union

    with rasterio.open(dtm_path) as ds:
        f = max(1, int(np.ceil(max(ds.width, ds.height) / max_cells)))
        h, w = -(-ds.height // f), -(-ds.width // f)
        mask = ds.read_masks(1, out_shape=(h, w)) > 0
        tf = ds.transform @ ds.transform.scale(ds.width / w, ds.height / h)
    if not mask.any():
        return None
    polys = [
        shape(g) for g, v in features.shapes(mask.astype(np.uint8), mask=mask, transform=tf) if v
    ]
    geom = unary_union(polys).simplify(abs(tf.a) / 2, preserve_topology=True)
    tr = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(crs_wkt), "EPSG:4326", always_xy=True)

    def to_wgs84(c: np.ndarray) -> np.ndarray:
        return np.column_stack(tr.transform(c[:, 0], c[:, 1]))

    return mapping(shapely.transform(geom.buffer(0), to_wgs84))


def stac_item(
    job_id: str,
    out_dir: Path,
    plan: Mapping[str, Any],
    names: list[str],
    now: dt.datetime | None = None,
) -> dict[str, Any]:
    """A STAC Item for the outputs ``names`` in ``out_dir`` of the job ``job_id``."""
    out_dir = Path(out_dir)
    now = now or dt.datetime.now(dt.UTC)
    crs_wkt = plan.get("crs_wkt")
    props: dict[str, Any] = {"created": _iso(now)}
    first, last, from_header = acquisition_dates([t["path"] for t in plan["tiles"]])
    if from_header and first is not None and first == last:
        props["datetime"] = _iso(first)
    else:
        props["datetime"] = None
        start, end = first or now, last or now
        props["start_datetime"] = _iso(start)
        props["end_datetime"] = _iso(end if end > start else start)
    code = plan.get("crs")
    if crs_wkt:
        if code and str(code).startswith("EPSG:"):
            props["proj:code"] = code
        else:
            props["proj:code"] = None
            props["proj:wkt2"] = crs_wkt
    else:
        props["proj:code"] = None

    geometry, bbox = None, None
    if crs_wkt and "dtm.tif" in names:
        geometry = footprint(out_dir / "dtm.tif", crs_wkt)
        if geometry is not None:
            from shapely.geometry import shape

            bbox = list(shape(geometry).bounds)
    assets: dict[str, Any] = {}
    exts = {PROJECTION}
    for name in names:
        suffix = Path(name).suffix.lower()
        asset: dict[str, Any] = {
            "href": f"./{name}",
            "type": MEDIA_TYPES.get(suffix, "application/octet-stream"),
            "roles": ROLES.get(name, _default_role(name, suffix)),
        }
        path = out_dir / name
        if suffix == ".tif" and path.exists():
            asset.update(raster_asset(path))
            exts.add(RASTER)
        elif suffix in (".las", ".laz") and path.exists():
            asset.update(pointcloud_asset(path))
            exts.add(POINTCLOUD)
        assets[name] = asset
    item: dict[str, Any] = {
        "type": "Feature",
        "stac_version": STAC_VERSION,
        "stac_extensions": sorted(exts),
        "id": job_id,
        "geometry": geometry,
        "properties": props,
        "links": [
            {"rel": "self", "href": "./item.json", "type": "application/geo+json"},
            # outputs/item.json -> the job (its directory, or /jobs/{id} when served)
            {"rel": "parent", "href": f"../../{job_id}", "type": "application/json"},
        ],
        "assets": assets,
    }
    if bbox is not None:
        item["bbox"] = bbox
    return item
