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
from numpy.typing import NDArray

from terrasift.errors import ProcessingError
from terrasift.params import stage_params
from terrasift.tiling.blocks import BlockGrid
from terrasift.tiling.rasters import FLOAT_NODATA, RasterMosaic, bounded_raster_cache, job_transform

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


RASTERS = (*FLOAT_RASTERS, "coverage")


def write_raster(job_dir: str, name: str) -> str:
    """Task: mosaic every block's window of raster ``name`` (one of ``RASTERS``) into its COG.

    One task per raster, so a job's workers write them side by side and the
    terrain tasks start as soon as the DTM is out.
    """
    with bounded_raster_cache():
        return _write_raster(Path(job_dir), name)


def _write_raster(job: Path, name: str) -> str:
    if name not in RASTERS:
        raise ValueError(f"unknown raster {name!r}")
    target = job / "outputs" / f"{name}.tif"
    if target.exists():
        return target.name
    plan = _load(job, "plan.json")
    grid = BlockGrid(**plan["grid"])
    work = job / "work"
    work.mkdir(exist_ok=True)
    f = 1
    if name == "coverage":
        params = _load(job, "job.json")["params"]
        cell = float(stage_params(params, "vegetation").cell)
        f = int(
            round(cell / grid.resolution)
        )  # DTM cells per coverage cell (the grid is aligned to it)
        mosaic = RasterMosaic(
            work / target.name,
            width=grid.width // f,
            height=grid.height // f,
            transform=job_transform(grid.x0, grid.y_top, cell),
            crs=plan["crs_wkt"],
            dtype="uint8",
            nodata=COVERAGE_NODATA,
        )
    else:
        transform = job_transform(grid.x0, grid.y_top, grid.resolution)
        mosaic = RasterMosaic(
            work / target.name,
            width=grid.width,
            height=grid.height,
            transform=transform,
            crs=plan["crs_wkt"],
        )
    mosaic.fill_nodata()
    for path in _block_files(job):
        with np.load(path) as data:
            row_off, col_off, rows, cols = (int(v) for v in data["window"])
            if rows <= 0 or cols <= 0:
                continue
            if name == "coverage":
                cov = data["raster_coverage"]
                # cells outside the data reach are nodata, like the DTM's
                reach = ~np.isnan(data["raster_dtm"][::f, ::f][: cov.shape[0], : cov.shape[1]])
                mosaic.write(
                    row_off // f,
                    col_off // f,
                    np.where(reach, cov, COVERAGE_NODATA).astype(np.uint8),
                )
            elif name == "chm":
                mosaic.write(
                    row_off, col_off, np.clip(data["raster_dsm"] - data["raster_dtm"], 0, None)
                )
            else:
                mosaic.write(row_off, col_off, data[f"raster_{name}"])
    mosaic.close_as_cog(target, resampling="mode" if name == "coverage" else "average")
    return target.name


BAND_CELLS = (
    1 << 19
)  # DTM cells per band for slope and categories: memory follows this, not the job


def write_terrain(job_dir: str) -> list[str]:
    """Slope, categories and terrain objects from the job's mosaicked DTM (both terrain tasks)."""
    return [write_slope(job_dir), *write_categories(job_dir)]


def write_slope(job_dir: str) -> str:
    """Task: the slope raster from the job's mosaicked DTM.

    Slope is local, so it runs over bands of DTM rows (with a margin for its
    smoothing) and memory follows the band, not the job.
    """
    import rasterio

    from terrasift.workers import terrain

    job = Path(job_dir)
    out = job / "outputs"
    if (out / "slope.tif").exists():
        return "slope.tif"
    plan = _load(job, "plan.json")
    tparams = stage_params(_load(job, "job.json")["params"], "terrain")
    work = job / "work"
    work.mkdir(exist_ok=True)
    with bounded_raster_cache(), rasterio.open(out / "dtm.tif") as ds:
        height, width, res = ds.height, ds.width, abs(ds.transform.a)
        band = max(1, BAND_CELLS // width)
        margin = tparams.median_size // 2 + 2
        m = RasterMosaic(
            work / "slope.tif",
            width=width,
            height=height,
            transform=ds.transform,
            crs=plan["crs_wkt"],
        )
        for r in range(0, height, band):
            lo, hi = max(0, r - margin), min(height, r + band + margin)
            slope = terrain.slope_degrees(
                _read_rows(ds, lo, hi), res, tparams.median_size, tparams.smooth
            )
            m.write(r, 0, slope[r - lo : r - lo + min(band, height - r)])
        m.close_as_cog(out / "slope.tif")
    return "slope.tif"


def _read_rows(ds: Any, r0: int, r1: int) -> NDArray:
    from rasterio.windows import Window

    return (
        ds.read(1, window=Window(0, r0, ds.width, r1 - r0), masked=True)
        .filled(np.nan)
        .astype(np.float64)
    )


def write_categories(job_dir: str) -> list[str]:
    """Task: categories and terrain objects from the job's mosaicked DTM.

    Categories are local, so they are computed over bands of whole category
    tiles and memory follows the band. Objects are found on the whole job's
    category grid (one byte per 2 m tile per band), so an object crossing
    block or tile borders comes out once.
    """
    with bounded_raster_cache():
        return _write_categories(Path(job_dir))


def _write_categories(job: Path) -> list[str]:
    import rasterio

    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat

    out = job / "outputs"
    plan = _load(job, "plan.json")
    params = _load(job, "job.json")["params"]
    cparams = stage_params(params, "categories")
    names = []
    work = job / "work"
    work.mkdir(exist_ok=True)
    filters = feat.resolve_filters(params.get("features", "all"), params.get("filters") or {})
    with rasterio.open(out / "dtm.tif") as ds:
        transform, height, width = ds.transform, ds.height, ds.width
        rows = max(1, BAND_CELLS // width)  # DTM rows per band: memory follows this, not the job

        def grid(step: float | None) -> cat.Categories:
            return cat.categories_by_bands(
                lambda r0, r1: _read_rows(ds, r0, r1), height, abs(transform.a), cparams, rows, step
            )

        cats = grid(None)
        stepped = {st: grid(st) for st in feat.step_sizes(filters)}
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

    if filters:
        result = feat.detect_features(
            cats,
            filters,
            transform,
            cats.tile_size,
            stage_params(params, "features"),
            stepped=stepped,
        )
        crs = plan["crs_wkt"]
        native = feat.features_geojson(result, crs, job.name, to_wgs84=False) if crs else None
        if native is not None:
            _write_json(out / "features.native.geojson", native)
            _write_json(
                out / "features.geojson",
                feat.features_geojson(result, crs, job.name, to_wgs84=True),
            )
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
        raise ProcessingError(
            f"{name}: {missing} points got no label and {twice} got more than one"
        )
    tmp = out.with_name(out.name + ".part")
    with laspy.open(tile["path"]) as reader:
        header = copy.deepcopy(reader.header)
        if str(header.version) == "1.0":
            # laspy writes from 1.1 on; 1.0 and 1.2 share the header and point
            # records of formats 0 and 1, so the copy is written as 1.2.
            header.version = laspy.header.Version(1, 2)
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
    job_dir: Path,
    plan: Mapping[str, Any],
    params: Mapping[str, Any],
    block_stats: list[dict],
    timings: Mapping[str, float],
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
    from terrasift.params import effective_stage_params
    from terrasift.workers import terrain, vegetation

    bins = {"empty": 0, "open": 0, "bush": 0, "tree": 0}
    for s in block_stats:
        for k in bins:
            bins[k] += s.get("vegetation", {}).get(k, 0)
    tree_cov, bush_cov = vegetation.coverage_from_counts(bins)
    rough = terrain.combine(
        terrain.Roughness(*s["roughness_sums"]) for s in block_stats if "roughness_sums" in s
    )
    steep = [s for s in block_stats if s.get("steep", {}).get("rotated")]
    mixed = [s["mixed"] for s in block_stats if "mixed" in s]
    report = {
        "job": job.name,
        "points": points,
        "tiles": [Path(t["path"]).name for t in plan["tiles"]],
        "crs": plan["crs"],
        "blocks": len(block_stats),
        "block_buffer": plan["grid"][
            "buffer"
        ],  # metres; resolved when the buffer parameter is auto
        "counts_per_class": dict(sorted(counts.items(), key=lambda kv: int(kv[0]))),
        "vegetation": {
            "tree_coverage": tree_cov,
            "bush_coverage": bush_cov,
            "bins": bins,
            "nogo_bins": sum(s.get("vegetation_nogo", 0) for s in block_stats),
        },
        "roughness": {
            **rough.to_dict(),
            "cell": max((s.get("roughness_cell", 0) for s in block_stats), default=None),
        },
        "roughness_per_block": {
            s["name"]: terrain.Roughness(*s["roughness_sums"]).to_dict()
            for s in block_stats
            if "roughness_sums" in s
        },
        "steep_blocks": {
            "tested": sum(1 for s in block_stats if s.get("steep")),
            "rotated": len(steep),
            "blocks": {s["name"]: s["steep"] for s in steep},
        },
        "mixed_measurements": (
            {
                "marked": sum(m["marked"] for m in mixed),
                "unclassified": sum(m["unclassified"] for m in mixed),
            }
            if mixed
            else "not run: no sensor_origin given"
        ),
        "low_points": sum(s.get("low_points", 0) for s in block_stats),
        "parameters": dict(params),
        "stage_parameters": effective_stage_params(params),
        "timings_seconds": {
            "job": dict(timings),
            "stages_summed_over_blocks": stage_times,
        },
        "points_per_second": points / timings["total"] if timings.get("total") else None,
        "warnings": list(plan.get("warnings", [])),
    }
    _write_json(out / "steep_blocks.geojson", steep_blocks_geojson(plan, steep))
    tmp = out / "report.json.part"
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, out / "report.json")
    names = sorted(
        p.name for p in out.iterdir() if not p.name.endswith(".part") and p.name != "item.json"
    )
    item = stac_item(job.name, plan, names)
    tmp = out / "item.json.part"
    tmp.write_text(json.dumps(item, indent=2))
    os.replace(tmp, out / "item.json")
    return sorted([*names, "item.json"])


def steep_blocks_geojson(plan: Mapping[str, Any], steep_stats: list[dict]) -> dict[str, Any]:
    """Blocks that went through rotated classification, as RFC 7946 polygons (WGS 84 when the CRS is known)."""
    from terrasift.tiling.blocks import parse_block_name

    grid = BlockGrid(**plan["grid"])
    tf = None
    if plan.get("crs_wkt"):
        tf = pyproj.Transformer.from_crs(
            pyproj.CRS.from_wkt(plan["crs_wkt"]), "EPSG:4326", always_xy=True
        )
    feats = []
    for s in steep_stats:
        ix, iy = parse_block_name(s["name"])
        x0, y0, x1, y1 = grid.core_bounds(ix, iy)
        ring = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
        if tf is not None:
            ring = [tf.transform(x, y) for x, y in ring]
        feats.append(
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [[list(p) for p in ring]]},
                "properties": {
                    "block": s["name"],
                    "facet_share": s["steep"].get("facet_share"),
                    "points_added_per_rotation": s["steep"].get("added_per_rotation", []),
                    "points": s.get("points_core"),
                },
            }
        )
    return {"type": "FeatureCollection", "features": feats}


def stac_item(job_id: str, plan: Mapping[str, Any], names: list[str]) -> dict[str, Any]:
    """A STAC 1.0 Item with the projection extension describing the job's outputs."""
    grid = BlockGrid(**plan["grid"])
    xmin, ymin = grid.x0, grid.y0
    xmax, ymax = grid.x0 + grid.width * grid.resolution, grid.y_top
    bbox_native = [xmin, ymin, xmax, ymax]
    geometry = None
    bbox = None
    if plan.get("crs_wkt"):
        tf = pyproj.Transformer.from_crs(
            pyproj.CRS.from_wkt(plan["crs_wkt"]), "EPSG:4326", always_xy=True
        )
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
        asset: dict[str, Any] = {
            "href": f"./{name}",
            "type": MEDIA_TYPES.get(suffix, "application/octet-stream"),
            "roles": [role],
        }
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
