"""Finishing tasks of a job: mosaics to COGs, classified LAZ in original order, report, STAC item.

Each writes to a temporary name and renames, and is skipped when its output
already exists, so a resumed job repeats only what is missing.
"""

from __future__ import annotations

import copy
import datetime as dt
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyproj

from terrasift.errors import ProcessingError
from terrasift.tiling.blocks import BlockGrid
from terrasift.params import stage_params
from terrasift.tiling.rasters import FLOAT_NODATA, RasterMosaic, job_transform

MEDIA_TYPES = {
    ".tif": "image/tiff; application=geotiff; profile=cloud-optimized",
    ".laz": "application/vnd.laszip",
    ".geojson": "application/geo+json",
    ".json": "application/json",
}

#: the float rasters every job writes; name -> how to make it from a block's arrays
FLOAT_RASTERS = ("dtm", "dsm", "chm")
COVERAGE_NODATA = 255


def _load(job_dir: Path, name: str) -> Any:
    return json.loads((job_dir / name).read_text())


def _block_files(job_dir: Path) -> list[Path]:
    return sorted((job_dir / "blocks").glob("*.npz"), key=lambda p: p.name)


def write_rasters(job_dir: str) -> list[str]:
    """Task: mosaic every block's raster windows into the job's COGs (DTM, DSM, CHM, coverage)."""
    job = Path(job_dir)
    wanted = [f"{n}.tif" for n in FLOAT_RASTERS] + ["coverage.tif"]
    out = job / "outputs"
    if all((out / w).exists() for w in wanted):
        return wanted
    plan = _load(job, "plan.json")
    params = _load(job, "job.json")["params"]
    grid = BlockGrid(**plan["grid"])
    transform = job_transform(grid.x0, grid.y_top, grid.resolution)
    work = job / "work"
    work.mkdir(exist_ok=True)
    mosaics = {
        n: RasterMosaic(work / f"{n}.tif", width=grid.width, height=grid.height, transform=transform, crs=plan["crs_wkt"])
        for n in FLOAT_RASTERS
    }
    cell = float(stage_params(params, "vegetation").cell)
    f = int(round(cell / grid.resolution))  # DTM cells per coverage cell (the grid is aligned to it)
    coverage = RasterMosaic(
        work / "coverage.tif",
        width=grid.width // f,
        height=grid.height // f,
        transform=job_transform(grid.x0, grid.y_top, cell),
        crs=plan["crs_wkt"],
        dtype="uint8",
        nodata=COVERAGE_NODATA,
    )
    for m in [*mosaics.values(), coverage]:
        m.fill_nodata()
    for path in _block_files(job):
        with np.load(path) as data:
            row_off, col_off, rows, cols = (int(v) for v in data["window"])
            if rows <= 0 or cols <= 0:
                continue
            dtm = data["raster_dtm"]
            dsm = data["raster_dsm"]
            arrays = {"dtm": dtm, "dsm": dsm, "chm": np.clip(dsm - dtm, 0, None)}
            for n, m in mosaics.items():
                m.write(row_off, col_off, arrays[n])
            cov = data["raster_coverage"]
            # cells outside the data reach are nodata, like the DTM's
            reach = ~np.isnan(dtm[:: f, :: f][: cov.shape[0], : cov.shape[1]])
            coverage.write(row_off // f, col_off // f, np.where(reach, cov, COVERAGE_NODATA).astype(np.uint8))
    for n, m in mosaics.items():
        m.close_as_cog(out / f"{n}.tif")
    coverage.close_as_cog(out / "coverage.tif", resampling="mode")
    return wanted


def write_terrain(job_dir: str) -> list[str]:
    """Task: slope, categories and terrain objects from the job's mosaicked DTM.

    Runs on the whole job's DTM so that objects crossing block or tile borders
    come out once. Needs the DTM in memory: 4 bytes per cell.
    """
    import rasterio

    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat
    from terrasift.workers import terrain

    job = Path(job_dir)
    out = job / "outputs"
    plan = _load(job, "plan.json")
    params = _load(job, "job.json")["params"]
    with rasterio.open(out / "dtm.tif") as ds:
        dtm = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        transform = ds.transform
    names = []
    work = job / "work"
    work.mkdir(exist_ok=True)
    res = abs(transform.a)
    if not (out / "slope.tif").exists():
        slope = terrain.slope_degrees(dtm, res, int(params.get("terrain.median_size", 3)))
        m = RasterMosaic(work / "slope.tif", width=dtm.shape[1], height=dtm.shape[0], transform=transform, crs=plan["crs_wkt"])
        m.write(0, 0, slope)
        m.close_as_cog(out / "slope.tif")
    names.append("slope.tif")

    cparams = stage_params(params, "categories")
    cats = cat.compute_categories(dtm, res, cparams)
    if not (out / "categories.tif").exists():
        bands = cats.bands()
        m = RasterMosaic(
            work / "categories.tif",
            width=bands.shape[2],
            height=bands.shape[1],
            transform=cats.transform(transform),
            crs=plan["crs_wkt"],
            dtype="uint8",
            nodata=cat.NODATA,
            count=4,
            descriptions=("inclination", "orientation", "state", "height_x10"),
        )
        m.write(0, 0, bands)
        m.close_as_cog(out / "categories.tif", resampling="nearest")
    names.append("categories.tif")

    filters = feat.resolve_filters(params.get("features", "all"), params.get("filters") or {})
    if filters:
        result = feat.detect_features(cats, filters, transform, cats.tile_size, stage_params(params, "features"))
        crs = plan["crs_wkt"]
        native = feat.features_geojson(result, crs, job.name, to_wgs84=False) if crs else None
        if native is not None:
            _write_json(out / "features.native.geojson", native)
            _write_json(out / "features.geojson", feat.features_geojson(result, crs, job.name, to_wgs84=True))
            names += ["features.geojson", "features.native.geojson"]
        for fname, marks in result.marked.items():
            m = RasterMosaic(
                work / f"{fname}.tif",
                width=marks.shape[1],
                height=marks.shape[0],
                transform=cats.transform(transform),
                crs=crs,
                dtype="uint8",
                nodata=255,
            )
            m.write(0, 0, np.where(cats.nodata, 255, marks.astype(np.uint8)))
            m.close_as_cog(out / f"{fname}.tif", resampling="nearest")
            names.append(f"{fname}.tif")
    return names


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def classified_name(plan: Mapping[str, Any], tile_index: int) -> str:
    """``classified.laz`` for a one-tile job, ``classified-<stem>.laz`` per tile otherwise."""
    if len(plan["tiles"]) == 1:
        return "classified.laz"
    return f"classified-{Path(plan['tiles'][tile_index]['path']).stem}.laz"


def write_classified(job_dir: str, tile_index: int, chunk_size: int = 1_000_000) -> str:
    """Task: copy tile ``tile_index`` with the job's classes, every point in order, every dimension kept."""
    job = Path(job_dir)
    plan = _load(job, "plan.json")
    name = classified_name(plan, tile_index)
    out = job / "outputs" / name
    if out.exists():
        return name
    tile = plan["tiles"][tile_index]
    n = int(tile["point_count"])
    labels = np.zeros(n, np.uint8)
    seen = np.zeros(n, np.uint8)
    for path in _block_files(job):
        with np.load(path) as data:
            mine = data["tile"] == tile_index
            idx = data["index"][mine]
            labels[idx] = data["classes"][mine]
            np.add.at(seen, idx, 1) if idx.size < 4096 else _count(seen, idx)
    if not (seen == 1).all():
        missing, twice = int((seen == 0).sum()), int((seen > 1).sum())
        raise ProcessingError(f"{name}: {missing} points got no label and {twice} got more than one")
    tmp = out.with_name(out.name + ".part")
    with laspy.open(tile["path"]) as reader:
        header = copy.deepcopy(reader.header)
        params = _load(job, "job.json")["params"]
        if params.get("crs"):
            header.add_crs(pyproj.CRS.from_user_input(params["crs"]))
        with laspy.open(str(tmp), mode="w", header=header, do_compress=True) as writer:
            start = 0
            for pts in reader.chunk_iterator(chunk_size):
                pts.classification = labels[start : start + len(pts)]
                writer.write_points(pts)
                start += len(pts)
    os.replace(tmp, out)
    return name


def _count(seen: np.ndarray, idx: np.ndarray) -> None:
    u, c = np.unique(idx, return_counts=True)
    seen[u] += c.astype(np.uint8)


def write_report_and_item(
    job_dir: Path, plan: Mapping[str, Any], params: Mapping[str, Any], block_stats: list[dict], timings: Mapping[str, float]
) -> list[str]:
    """Write ``report.json`` and ``item.json``; return every output name of the job."""
    job = Path(job_dir)
    out = job / "outputs"
    counts: dict[str, int] = {}
    stage_times: dict[str, float] = {}
    for s in block_stats:
        for c, v in s.get("counts", {}).items():
            counts[c] = counts.get(c, 0) + v
        for k, v in s.get("timings", {}).items():
            stage_times[k] = stage_times.get(k, 0.0) + v
    points = sum(int(t["point_count"]) for t in plan["tiles"])
    report = {
        "job": job.name,
        "points": points,
        "tiles": [Path(t["path"]).name for t in plan["tiles"]],
        "crs": plan["crs"],
        "blocks": len(block_stats),
        "counts_per_class": dict(sorted(counts.items(), key=lambda kv: int(kv[0]))),
        "parameters": dict(params),
        "timings_seconds": {
            "job": dict(timings),
            "stages_summed_over_blocks": stage_times,
        },
        "points_per_second": points / timings["total"] if timings.get("total") else None,
        "warnings": list(plan.get("warnings", [])),
    }
    tmp = out / "report.json.part"
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, out / "report.json")
    names = sorted(p.name for p in out.iterdir() if not p.name.endswith(".part") and p.name != "item.json")
    item = stac_item(job.name, plan, names)
    tmp = out / "item.json.part"
    tmp.write_text(json.dumps(item, indent=2))
    os.replace(tmp, out / "item.json")
    return sorted([*names, "item.json"])


def stac_item(job_id: str, plan: Mapping[str, Any], names: list[str]) -> dict[str, Any]:
    """A STAC 1.0 Item with the projection extension describing the job's outputs."""
    grid = BlockGrid(**plan["grid"])
    xmin, ymin = grid.x0, grid.y0
    xmax, ymax = grid.x0 + grid.width * grid.resolution, grid.y_top
    bbox_native = [xmin, ymin, xmax, ymax]
    geometry = None
    bbox = None
    if plan.get("crs_wkt"):
        tf = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(plan["crs_wkt"]), "EPSG:4326", always_xy=True)
        lon0, lat0, lon1, lat1 = tf.transform_bounds(xmin, ymin, xmax, ymax)
        bbox = [lon0, lat0, lon1, lat1]
        geometry = {
            "type": "Polygon",
            "coordinates": [[[lon0, lat0], [lon1, lat0], [lon1, lat1], [lon0, lat1], [lon0, lat0]]],
        }
    transform = [grid.resolution, 0.0, grid.x0, 0.0, -grid.resolution, grid.y_top]
    props: dict[str, Any] = {
        "datetime": dt.datetime.now(dt.UTC).isoformat().replace("+00:00", "Z"),
        "proj:bbox": bbox_native,
        "proj:shape": [grid.height, grid.width],
        "proj:transform": transform,
    }
    code = plan.get("crs")
    if code and code.startswith("EPSG:"):
        props["proj:code"] = code
    elif plan.get("crs_wkt"):
        props["proj:code"] = None
        props["proj:wkt2"] = plan["crs_wkt"]
    assets = {}
    for name in names:
        suffix = Path(name).suffix
        role = "metadata" if suffix == ".json" else "data"
        asset: dict[str, Any] = {"href": f"./{name}", "type": MEDIA_TYPES.get(suffix, "application/octet-stream"), "roles": [role]}
        if suffix == ".tif":
            asset["proj:shape"] = [grid.height, grid.width]
            asset["proj:transform"] = transform
            asset["nodata"] = FLOAT_NODATA
        assets[name] = asset
    return {
        "type": "Feature",
        "stac_version": "1.0.0",
        "stac_extensions": ["https://stac-extensions.github.io/projection/v2.0.0/schema.json"],
        "id": job_id,
        "bbox": bbox,
        "geometry": geometry,
        "properties": props,
        "links": [],
        "assets": assets,
    }
