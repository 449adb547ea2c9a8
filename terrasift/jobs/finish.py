"""Finishing tasks of a job: mosaics to COGs, slope, categories and features over the mosaic, classified LAZ.

Each writes to a temporary name and renames, and is skipped when its output
already exists, so a resumed job repeats only what is missing.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from terrasift.errors import ProcessingError
from terrasift.files import load_json, write_json
from terrasift.jobs.dirs import block_results
from terrasift.jobs.params import stage_params
from terrasift.tiling.blocks import BlockGrid, parse_block_name
from terrasift.tiling.classified import write_classified_copy
from terrasift.tiling.rasters import (
    RasterMosaic,
    band_metadata,
    bounded_raster_cache,
    job_transform,
)

#: the float rasters every job writes; name -> how to make it from a block's arrays
FLOAT_RASTERS = ("dtm", "dsm", "chm")
COVERAGE_NODATA = 255


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
    plan = load_json(job / "plan.json")
    grid = BlockGrid(**plan["grid"])
    work = job / "work"
    work.mkdir(exist_ok=True)
    f = 1
    if name == "coverage":
        params = load_json(job / "job.json")["params"]
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
            **band_metadata("coverage"),
        )
    else:
        transform = job_transform(grid.x0, grid.y_top, grid.resolution)
        mosaic = RasterMosaic(
            work / target.name,
            width=grid.width,
            height=grid.height,
            transform=transform,
            crs=plan["crs_wkt"],
            **band_metadata(name),
        )
    mosaic.fill_nodata()
    for path in block_results(job):
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
            elif name == "chm" and "raster_chm" not in data:
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
    plan = load_json(job / "plan.json")
    tparams = stage_params(load_json(job / "job.json")["params"], "terrain")
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
            **band_metadata("slope"),
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


#: side (metres) of the squares terrain objects are searched on, each with a halo of
#: the filters' reach (~190 m for the built-in filters at 0.5 m): memory follows one
#: square and its halo, not the job; wider squares redo less of their halo
FEATURE_CORE_M = 768.0


def feature_squares(
    height: int, width: int, side: int, spans: list[tuple[int, int, int, int]] | None = None
) -> dict[str, tuple[int, int, int, int]]:
    """Squares of ``side`` cells over a DTM of ``height`` × ``width`` (row0, col0, row1,
    col1; ends excluded), named ``<row>_<col>``; only those overlapping ``spans`` when given."""
    out = {}
    for i in range(0, height, side):
        for j in range(0, width, side):
            core = (i, j, min(height, i + side), min(width, j + side))
            if spans is None or any(
                core[0] < w[2] and w[0] < core[2] and core[1] < w[3] and w[1] < core[3]
                for w in spans
            ):
                out[f"{i // side}_{j // side}"] = core
    return out


def write_categories(job_dir: str) -> list[str]:
    """Task: categories and terrain objects from the job's mosaicked DTM.

    Categories are local, so they are computed over bands of whole category
    tiles and memory follows the band. Objects are searched square by square
    (``FEATURE_CORE_M``, each with a halo grown around any object that needs
    it: ``workers/features/tiled.py``) and their pieces joined, so memory
    follows a square and an object crossing block, tile or square borders
    comes out once, as one search over the whole DTM finds it.
    """
    with bounded_raster_cache():
        return _write_categories(Path(job_dir))


def dtm_category_grids(ds: Any, cparams: Any, filters: list) -> tuple[Any, dict, Any]:
    """The category grid of an open DTM and the grids the ``filters`` search (by their
    step and regional window), read in bands; with the parameters used, whose ``noise``
    and ``slope_noise`` are the ones given or else measured on this DTM."""
    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat

    transform, height, width = ds.transform, ds.height, ds.width
    rows = max(1, BAND_CELLS // width)  # DTM rows per band: memory follows this, not the job

    def grids(step: float | None, windows: list[float | None]) -> list[cat.Categories]:
        return cat.categories_by_bands(
            lambda r0, r1: _read_rows(ds, r0, r1),
            height,
            abs(transform.a),
            cparams,
            rows,
            step,
            windows,
        )

    keys = feat.grid_keys(filters)
    if cparams.noise is None:  # every grid judges flatness against the DTM's own noise
        cparams = cparams.model_copy(
            update={
                "noise": cat.measure_noise_by_bands(
                    lambda r0, r1: _read_rows(ds, r0, r1),
                    height,
                    abs(transform.a),
                    cparams,
                    rows,
                )
            }
        )
    if cparams.slope_noise is None:  # and against one slope noise
        cparams = cparams.model_copy(
            update={
                "slope_noise": 0.0
                if cparams.noise == 0
                else cat.measure_slope_noise_by_bands(
                    lambda r0, r1: _read_rows(ds, r0, r1),
                    height,
                    abs(transform.a),
                    cparams,
                    rows,
                )
            }
        )
    stepped: dict = {}
    cats = None
    for step in sorted({k[0] for k in keys} | {None}, key=lambda v: v or 0.0):
        # the grids of one step share their plane fits
        mine = [k for k in keys if k[0] == step]
        windows = [w for _, w in mine]
        if step is None:
            windows = [None, *windows]
        made = grids(step, windows)
        if step is None:
            cats, made = made[0], made[1:]
        stepped.update(zip(mine, made, strict=True))
    assert cats is not None
    return cats, stepped, cparams


def _write_categories(job: Path) -> list[str]:
    import rasterio

    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat

    out = job / "outputs"
    plan = load_json(job / "plan.json")
    params = load_json(job / "job.json")["params"]
    cparams = stage_params(params, "categories")
    names = []
    work = job / "work"
    work.mkdir(exist_ok=True)
    filters = feat.resolve_filters(params.get("features", "all"), params.get("filters") or {})
    # filters of objects run square by square; those marking tiles on the whole grid
    objects = [f for f in filters if f.connect is not None or f.rectangle is not None]
    marking = [f for f in filters if f.connect is None and f.rectangle is None]
    fparams = stage_params(params, "features")
    with rasterio.open(out / "dtm.tif") as ds:
        transform = ds.transform
        cats, stepped, cparams = dtm_category_grids(ds, cparams, marking)
        pieces = _square_pieces(ds, objects, cparams, fparams) if objects else []
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
            **band_metadata("categories"),
        )
        m.write(0, 0, bands)
        m.close_as_cog(out / "categories.tif", resampling="nearest")
    names.append("categories.tif")

    if filters:
        from terrasift.workers.features import tiled

        result = feat.detect_features(
            cats, marking, transform, cats.tile_size, fparams, stepped=stepped
        )
        result.objects = tiled.merge_pieces(
            pieces, objects, cparams, abs(transform.a), fparams, dtm_window(out / "dtm.tif")
        ).objects
        crs = plan["crs_wkt"]
        # Tile CRS: a GeoPackage (OGR reads its CRS) and a GeoJSON naming its
        # CRS; WGS 84 (RFC 7946) only when the CRS is known.
        from terrasift.tiling.vectors import crs_member, write_geopackage

        native = feat.features_geojson(result, crs or 0, job.name, to_wgs84=False)
        write_geopackage(out / "features.gpkg", native, crs)
        member = crs_member(crs)
        write_json(
            out / "features.native.geojson", {**native, **({"crs": member} if member else {})}
        )
        names += ["features.gpkg", "features.native.geojson"]
        if crs:
            write_json(
                out / "features.geojson",
                feat.features_geojson(result, crs, job.name, to_wgs84=True),
            )
            names.append("features.geojson")
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


def dtm_window(path: Path) -> Any:
    """A reader of the DTM at ``path`` around map bounds (``features.edges.Reader``): the
    window's heights (NaN for no data) and its geotransform."""

    def read(bounds: tuple[float, float, float, float]) -> tuple[NDArray, Any]:
        import rasterio
        from rasterio.windows import from_bounds

        with rasterio.open(path) as ds:
            w = from_bounds(*bounds, transform=ds.transform).round_offsets().round_lengths()
            w = w.intersection(rasterio.windows.Window(0, 0, ds.width, ds.height))
            z = ds.read(1, window=w, masked=True).filled(np.nan).astype(np.float64)
            return z, ds.window_transform(w)

    return read


def _square_pieces(ds: Any, filters: list, cparams: Any, fparams: Any) -> list:
    """The object pieces of an open DTM, searched square by square (``tiled.tile_pieces``)."""
    from rasterio.windows import Window

    from terrasift.workers.features import tiled

    def read(r0: int, r1: int, c0: int, c1: int) -> NDArray:
        return (
            ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
            .filled(np.nan)
            .astype(np.float64)
        )

    side = max(1, int(round(FEATURE_CORE_M / abs(ds.transform.a))))
    pieces: list = []
    for core in feature_squares(ds.height, ds.width, side).values():
        pieces += tiled.tile_pieces(
            read, (ds.height, ds.width), ds.transform, core, filters, cparams, fparams
        )
    return pieces


def classified_name(plan: Mapping[str, Any], tile_index: int) -> str:
    """``classified.laz`` for a one-tile job, ``classified-<stem>.laz`` per tile otherwise."""
    if len(plan["tiles"]) == 1:
        return "classified.laz"
    return f"classified-{Path(plan['tiles'][tile_index]['path']).stem}.laz"


def write_classified(job_dir: str, tile_index: int, chunk_size: int = 1_000_000) -> str:
    """Task: copy tile ``tile_index`` with the job's classes, every point in order, every dimension kept."""
    job = Path(job_dir)
    plan = load_json(job / "plan.json")
    name = classified_name(plan, tile_index)
    out = job / "outputs" / name
    if out.exists():
        return name
    tile = plan["tiles"][tile_index]
    n = int(tile["point_count"])
    # The blocks under the tile's header box first; all blocks when that box
    # lied (points outside it) and some points are still without a label.
    mine_blocks = BlockGrid(**plan["grid"]).blocks_over(tile["mins"], tile["maxs"])
    labels, seen = _gather_classes(job, tile_index, n, mine_blocks)
    if not (seen == 1).all():
        labels, seen = _gather_classes(job, tile_index, n, None)
    if not (seen == 1).all():
        missing, twice = int((seen == 0).sum()), int((seen > 1).sum())
        raise ProcessingError(
            f"{name}: {missing} points got no label and {twice} got more than one"
        )
    params = load_json(job / "job.json")["params"]
    write_classified_copy(
        tile["path"],
        out,
        labels,
        crs=params.get("crs"),
        chunk_size=chunk_size,
        roots=plan.get("input_roots"),
    )
    return name


def _gather_classes(
    job: Path, tile_index: int, n: int, blocks: set[tuple[int, int]] | None
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Classes of the tile's ``n`` points from the block results (of ``blocks``
    only, when given), and how many results labelled each point."""
    labels = np.zeros(n, np.uint8)
    seen = np.zeros(n, np.uint8)
    for path in block_results(job):
        if blocks is not None and parse_block_name(path.stem) not in blocks:
            continue
        with np.load(path) as data:
            mine = data["tile"] == tile_index
            idx = data["index"][mine]
            labels[idx] = data["classes"][mine]
            np.add.at(seen, idx, 1) if idx.size < 4096 else _count(seen, idx)
    return labels, seen


def _count(seen: np.ndarray, idx: np.ndarray) -> None:
    u, c = np.unique(idx, return_counts=True)
    seen[u] += c.astype(np.uint8)
