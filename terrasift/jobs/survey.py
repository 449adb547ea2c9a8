"""Survey runs: one current product per survey, updated by incremental runs that stay seamless.

A survey is a set of named tiles. Its product lives in ``<survey>/product/``:
version folders ``v-<job>/`` and a ``current`` symlink switched atomically by
each run. A version holds ``tiles/<stem>/`` (per-tile COGs, classified LAZ,
STAC Item), VRT mosaics over them (``dtm.vrt`` ...), ``features.geojson``
merged over the whole survey, ``collection.json`` and ``state.json`` (what the
product was made from: checksums, parameters, and the survey's fixed density,
block-grid anchor and category noise).

A run is an ordinary job over *source* tiles with a block grid anchored on the
survey (not on the run), the survey's density and only the blocks that cover
the *output* tiles. Output tiles are the tiles some block of which sees a
changed tile (checksum, parameters, added or removed) within its core or halo;
source tiles are every tile any of those blocks reads points from. Each block
therefore reads exactly the points it reads in a full run, in the same order
(tiles by name), so its result is the same, and a tile's result does not
depend on which tiles ran with it. Unchanged tiles' files are hard links into
the new version. Slope and categories (with the survey's fixed noise) are
made per tile from the new DTM mosaic, only for tiles within the slope's
margin of changed cells; features are searched over the whole survey's
category grids, since an object may cross any number of tile edges.

A run reads at most ``max_points`` points: a larger set of output tiles is
taken in batches (``pending`` in ``state.json`` carries the rest to the next
run), and the last batch's product equals one run over all tiles.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import math
import os
import shutil
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from terrasift.errors import InputError, NothingChanged, ProcessingError
from terrasift.files import load_json, write_json
from terrasift.jobs.dirs import block_result_path
from terrasift.jobs.params import grid_alignment, resolve_buffer, stage_params
from terrasift.jobs.plan import _crs_label, read_headers, resolve_crs
from terrasift.tiling.blocks import BlockGrid, block_name
from terrasift.tiling.classified import write_classified_copy
from terrasift.tiling.rasters import (
    FLOAT_NODATA,
    RasterMosaic,
    band_metadata,
    bounded_raster_cache,
    job_transform,
)
from terrasift.tiling.vrt import VrtSource, write_vrt

PRODUCT = "product"
CURRENT = "current"
STATE = "state.json"
#: mosaics of a survey product, each a VRT over ``tiles/<stem>/<name>.tif``
MOSAICS = ("dtm", "dsm", "chm", "slope", "coverage", "categories")
#: per-tile rasters made from block results (the rest come from the DTM mosaic)
BLOCK_RASTERS = ("dtm", "dsm", "chm", "coverage")
COVERAGE_NODATA = 255
#: side (metres) of the squares the feature search runs on, each with a halo of the
#: filters' reach (~190 m for the built-in filters at 0.5 m): memory follows one square
#: and its halo, not the survey; wider squares redo less of their halo
FEATURE_CORE_M = 768.0
Bounds = tuple[float, float, float, float]
Window = tuple[int, int, int, int]  # row_off, col_off, rows, cols in the survey grid


def tile_name(path: str | Path) -> str:
    """A tile's name in its survey: its file name."""
    return Path(path).name


def tile_stem(name: str) -> str:
    return Path(name).stem


def product_root(survey_dir: Path) -> Path:
    return Path(survey_dir) / PRODUCT


def current_version(survey_dir: Path) -> Path | None:
    """The folder of the survey's current product, or None before the first run."""
    link = product_root(survey_dir) / CURRENT
    return link.resolve() if link.is_symlink() and link.resolve().is_dir() else None


def current_state(survey_dir: Path) -> dict[str, Any] | None:
    version = current_version(survey_dir)
    return None if version is None else load_json(version / STATE)


def file_checksum(path: Path, known: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """SHA-256 of a tile with its size and mtime; reused from ``known`` when both match."""
    st = Path(path).stat()
    if known and known.get("size") == st.st_size and known.get("mtime_ns") == st.st_mtime_ns:
        return {"sha256": known["sha256"], "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return {"sha256": h.hexdigest(), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def params_key(params: Mapping[str, Any]) -> str:
    """A digest of a run's validated parameters: tiles made with another key are stale."""
    text = json.dumps(dict(params), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def survey_grid(
    bounds: list[Bounds], anchor: tuple[float, float], params: Mapping[str, Any], buffer: float
) -> BlockGrid:
    """Whole blocks over every tile of the survey, laid from the survey's anchor.

    Blocks are never clipped by the raster's extent, so a block's result does
    not change when tiles far from it come or go.
    """
    res = float(params["resolution"])
    k = max(1, int(round(grid_alignment(params) / res)))
    step = k * res
    block_cells = k * max(1, int(round(float(params["block_size"]) / step)))
    size = block_cells * res
    ax = math.floor(anchor[0] / step) * step
    ay = math.floor(anchor[1] / step) * step
    x0 = ax + math.floor((min(b[0] for b in bounds) - ax) / size) * size
    y0 = ay + math.floor((min(b[1] for b in bounds) - ay) / size) * size
    nx = int(math.floor((max(b[2] for b in bounds) - x0) / size)) + 1
    ny = int(math.floor((max(b[3] for b in bounds) - y0) / size)) + 1
    return BlockGrid(x0, y0, res, nx * block_cells, ny * block_cells, size, buffer)


def tile_window(grid: BlockGrid, b: Bounds, k: int) -> Window:
    """Cells of the survey grid a tile owns: its bounds widened to whole alignment steps."""
    step = k * grid.resolution
    c0 = max(0, math.floor((b[0] - grid.x0) / step))
    c1 = min(grid.width // k, math.floor((b[2] - grid.x0) / step) + 1)
    j0 = max(0, math.floor((b[1] - grid.y0) / step))
    j1 = min(grid.height // k, math.floor((b[3] - grid.y0) / step) + 1)
    return grid.height - j1 * k, c0 * k, (j1 - j0) * k, (c1 - c0) * k


def window_bounds(grid: BlockGrid, w: Window) -> Bounds:
    row_off, col_off, rows, cols = w
    xmin = grid.x0 + col_off * grid.resolution
    ymax = grid.y_top - row_off * grid.resolution
    return xmin, ymax - rows * grid.resolution, xmin + cols * grid.resolution, ymax


def window_blocks(grid: BlockGrid, w: Window) -> list[tuple[int, int]]:
    """Blocks whose core overlaps window ``w``."""
    row_off, col_off, rows, cols = w
    c = grid.block_cells
    ix0, ix1 = col_off // c, (col_off + cols - 1) // c
    iy_top = (grid.height - row_off - 1) // c
    iy_bottom = (grid.height - row_off - rows) // c
    return [(ix, iy) for ix in range(ix0, ix1 + 1) for iy in range(iy_bottom, iy_top + 1)]


def _reach(grid: BlockGrid, ix: int, iy: int) -> Bounds:
    """A block's core widened by its buffer: where its points come from."""
    x0, y0 = grid.x0 + ix * grid.block_size, grid.y0 + iy * grid.block_size
    b = grid.buffer
    return x0 - b, y0 - b, x0 + grid.block_size + b, y0 + grid.block_size + b


def _overlaps(a: Bounds, b: Bounds) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def plan_survey_run(
    job_dir: Path,
    survey_dir: Path,
    files: list[Path],
    params: Mapping[str, Any],
    *,
    mode: str = "incremental",
    max_points: int | None = None,
    keep_intermediates: bool = False,
) -> dict[str, Any]:
    """Decide what a run redoes and write its ``job.json``; return a summary.

    ``keep_intermediates`` keeps the run's shards, block results and per-tile
    outputs after it published (by default they are removed then). Raises
    NothingChanged for an incremental run with nothing to do.
    """
    if mode not in ("incremental", "full"):
        raise InputError(f"mode must be 'incremental' or 'full', not {mode!r}")
    names = [tile_name(f) for f in files]
    if len(set(names)) != len(names):
        raise InputError("tiles of a survey need distinct file names")
    by_name = dict(sorted(zip(names, files, strict=True)))
    state = current_state(survey_dir) or {}
    old = state.get("tiles", {})
    infos = dict(zip(by_name, read_headers(list(by_name.values()), max_points), strict=True))
    crs_wkt, warnings = resolve_crs(list(infos.values()), params.get("crs"))
    sums = {n: file_checksum(p, old.get(n)) for n, p in by_name.items()}
    bounds: dict[str, Bounds] = {
        n: (i.mins[0], i.mins[1], i.maxs[0], i.maxs[1]) for n, i in infos.items()
    }
    # Fixed per survey at its first run: density (and the buffer that follows), anchor.
    density = state.get("density")
    if density is None:
        area = sum(max(i.area, 1.0) for i in infos.values())
        density = sum(i.point_count for i in infos.values()) / area
    anchor = tuple(
        state.get("anchor")
        or (min(b[0] for b in bounds.values()), min(b[1] for b in bounds.values()))
    )
    buffer, warning = resolve_buffer(params, density)
    if warning:
        warnings.append(warning)
    grid = survey_grid(list(bounds.values()), (anchor[0], anchor[1]), params, buffer)
    k = max(1, int(round(grid_alignment(params) / grid.resolution)))
    windows = {n: tile_window(grid, b, k) for n, b in bounds.items()}
    key = params_key(params)

    if (
        mode == "full"
        or not state
        or state.get("params_key") != key
        or state.get("grid_step")
        != [
            grid.block_size,
            grid.resolution,
        ]
    ):
        outputs = list(by_name)
        reason = "full" if mode == "full" or not state else "parameters changed"
    else:
        regions: list[Bounds] = []
        for n in by_name:
            if n not in old or old[n]["sha256"] != sums[n]["sha256"]:
                regions.append(bounds[n])
                if n in old:
                    regions.append(tuple(old[n]["bounds"]))
        regions += [tuple(o["bounds"]) for n, o in old.items() if n not in by_name]
        touched = {
            (ix, iy)
            for ix in range(grid.nx)
            for iy in range(grid.ny)
            if any(_overlaps(_reach(grid, ix, iy), r) for r in regions)
        }
        # tiles an earlier batch left for later, plus those this change makes stale
        left = set(state.get("pending", [])) & set(by_name)
        outputs = [
            n for n in by_name if n in left or touched & set(window_blocks(grid, windows[n]))
        ]
        reason = "incremental"
        if not outputs and not regions:
            raise NothingChanged(
                'no tile changed since the last run (send {"mode": "full"} to redo all)'
            )

    def reads(names: list[str]) -> list[str]:
        """Source tiles: every tile a block of the ``names`` tiles reads points from."""
        reaches = [
            _reach(grid, ix, iy)
            for ix, iy in {b for n in names for b in window_blocks(grid, windows[n])}
        ]
        return [m for m in by_name if any(_overlaps(bounds[m], r) for r in reaches)]

    outputs, pending = _batch(
        outputs, reads, {n: infos[n].point_count for n in by_name}, windows, max_points
    )
    needed = sorted({b for n in outputs for b in window_blocks(grid, windows[n])})
    sources = reads(outputs)
    base = current_version(survey_dir)
    tiles = {
        n: {
            "path": str(Path(by_name[n]).resolve()),
            **sums[n],
            "bounds": list(bounds[n]),
            "window": list(windows[n]),
            "points": infos[n].point_count,
        }
        for n in by_name
    }
    job = {
        "inputs": [tiles[n]["path"] for n in sources],
        "params": dict(params),
        "survey": {
            "dir": str(Path(survey_dir).resolve()),
            "base": None if base is None else base.name,
            "mode": reason,
            "grid": grid.to_dict(),
            "density": density,
            "anchor": list(anchor),
            "crs_wkt": crs_wkt,
            "warnings": warnings,
            "params_key": key,
            "noise": state.get("noise") if state.get("params_key") == key else None,
            "slope_noise": state.get("slope_noise") if state.get("params_key") == key else None,
            "tiles": tiles,
            "sources": sources,
            "outputs": outputs,
            "pending": pending,
            "blocks": [block_name(ix, iy) for ix, iy in needed],
            "keep_intermediates": bool(keep_intermediates),
        },
    }
    Path(job_dir).mkdir(parents=True, exist_ok=True)
    write_json(Path(job_dir) / "job.json", job, indent=2)
    return {
        "mode": reason,
        "outputs": outputs,
        "sources": sources,
        "blocks": len(needed),
        "pending": pending,
    }


def _batch(
    outputs: list[str],
    reads: Any,
    points: Mapping[str, int],
    windows: Mapping[str, Window],
    max_points: int | None,
) -> tuple[list[str], list[str]]:
    """The output tiles of this run and those left for the next (``pending``).

    A run reads at most ``max_points`` points (its source tiles, halo included):
    output tiles are taken row by row across the survey while their sources fit,
    so one batch reads a compact area and neighbouring batches share few sources.
    The product of the last batch equals a run of all tiles at once, since every
    block still reads exactly the tiles it reads in a full run.
    """
    if max_points is None or sum(points[n] for n in reads(outputs)) <= max_points:
        return outputs, []
    order = sorted(outputs, key=lambda n: (windows[n][0], windows[n][1], n))
    taken: list[str] = []
    sources: set[str] = set()
    for n in order:
        more = sources | set(reads([n]))
        if sum(points[m] for m in more) > max_points:
            break
        taken.append(n)
        sources = more
    if not taken:
        first = order[0]
        total = sum(points[m] for m in reads([first]))
        raise InputError(
            f"{first} with the neighbours its halo reads holds {total} points; "
            f"a run takes at most {max_points}"
        )
    chosen = set(taken)
    return [n for n in outputs if n in chosen], [n for n in outputs if n not in chosen]


def survey_plan(job_dir: Path, job: Mapping[str, Any]) -> dict[str, Any]:
    """``plan.json`` of a survey run: the survey's grid and density, the source tiles."""
    s = job["survey"]
    infos = read_headers(job["inputs"])
    return {
        "tiles": [dict(i.__dict__) for i in infos],
        "density": s["density"],
        "crs_wkt": s["crs_wkt"],
        "crs": _crs_label(s["crs_wkt"]),
        "grid": s["grid"],
        "warnings": list(s["warnings"]),
    }


# -- finishing tasks of a run ---------------------------------------------------------


def _run_out(job: Path, name: str) -> Path:
    return job / "outputs" / "tiles" / tile_stem(name)


def write_tile_rasters(job_dir: str, name: str) -> str:
    """Task: tile ``name``'s DTM, DSM, CHM and coverage COGs from the run's block results."""
    job = Path(job_dir)
    out = _run_out(job, name)
    if all((out / f"{r}.tif").exists() for r in BLOCK_RASTERS):
        return name
    spec = load_json(job / "job.json")
    s = spec["survey"]
    grid = BlockGrid(**s["grid"])
    row_off, col_off, rows, cols = s["tiles"][name]["window"]
    xmin, _, _, ymax = window_bounds(grid, (row_off, col_off, rows, cols))
    f = int(round(float(stage_params(spec["params"], "vegetation").cell) / grid.resolution))
    work = job / "work" / "tiles"
    work.mkdir(parents=True, exist_ok=True)
    stem = tile_stem(name)
    mosaics: dict[str, RasterMosaic] = {}
    with bounded_raster_cache():
        for r in BLOCK_RASTERS:
            fr = f if r == "coverage" else 1
            kw: dict[str, Any] = (
                {"dtype": "uint8", "nodata": COVERAGE_NODATA} if r == "coverage" else {}
            )
            mosaics[r] = RasterMosaic(
                work / f"{stem}-{r}.tif",
                width=cols // fr,
                height=rows // fr,
                transform=job_transform(xmin, ymax, grid.resolution * fr),
                crs=s["crs_wkt"],
                **kw,
                **band_metadata(r),
            )
            mosaics[r].fill_nodata()
        for ix, iy in window_blocks(grid, (row_off, col_off, rows, cols)):
            path = block_result_path(job, block_name(ix, iy))
            if not path.exists():
                continue  # a block no point fell in
            with np.load(path) as data:
                br, bc, bh, bw = (int(v) for v in data["window"])
                r0, r1 = max(br, row_off), min(br + bh, row_off + rows)
                c0, c1 = max(bc, col_off), min(bc + bw, col_off + cols)
                if r0 >= r1 or c0 >= c1:
                    continue
                arrays = {k: data[f"raster_{k}"] for k in ("dtm", "dsm")}
                arrays["chm"] = (
                    data["raster_chm"]
                    if "raster_chm" in data
                    else np.clip(arrays["dsm"] - arrays["dtm"], 0, None)
                )
                cov = data["raster_coverage"]
                reach = ~np.isnan(arrays["dtm"][::f, ::f][: cov.shape[0], : cov.shape[1]])
                arrays["coverage"] = np.where(reach, cov, COVERAGE_NODATA).astype(np.uint8)
            for r in BLOCK_RASTERS:
                fr = f if r == "coverage" else 1
                a = arrays[r][(r0 - br) // fr : (r1 - br) // fr, (c0 - bc) // fr : (c1 - bc) // fr]
                mosaics[r].write((r0 - row_off) // fr, (c0 - col_off) // fr, a)
        for r, m in mosaics.items():
            m.close_as_cog(out / f"{r}.tif", resampling="mode" if r == "coverage" else "average")
    return name


def write_tile_classified(job_dir: str, name: str, chunk_size: int = 1_000_000) -> str:
    """Task: tile ``name`` with the run's classes, every point in order, every dimension kept."""
    job = Path(job_dir)
    out = _run_out(job, name) / "classified.laz"
    if out.exists():
        return name
    spec = load_json(job / "job.json")
    s = spec["survey"]
    grid = BlockGrid(**s["grid"])
    index = s["sources"].index(name)
    tile = s["tiles"][name]
    n = int(tile["points"])
    labels = np.zeros(n, np.uint8)
    seen = np.zeros(n, np.int64)
    for ix, iy in window_blocks(grid, tuple(tile["window"])):
        path = block_result_path(job, block_name(ix, iy))
        if not path.exists():
            continue
        with np.load(path) as data:
            mine = data["tile"] == index
            idx = data["index"][mine]
            labels[idx] = data["classes"][mine]
            seen += np.bincount(idx, minlength=n)
    if not (seen == 1).all():
        raise ProcessingError(
            f"{name}: {int((seen == 0).sum())} points got no label and "
            f"{int((seen > 1).sum())} got more than one"
        )
    write_classified_copy(
        tile["path"], out, labels, crs=spec["params"].get("crs"), chunk_size=chunk_size
    )
    return name


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _link_tree(src: Path, dst: Path, skip: set[str] = frozenset()) -> None:  # type: ignore[assignment]
    dst.mkdir(parents=True, exist_ok=True)
    for p in src.iterdir():
        if p.is_file() and p.name not in skip and not p.name.startswith("."):
            os.link(p, dst / p.name)


#: per-tile files made again at every publish, from the survey's mosaics
DERIVED = {"slope.tif", "categories.tif", "item.json"}


def publish(job_dir: str) -> dict[str, Any]:
    """Task: make the run's new product version and switch ``current`` to it.

    Under the survey's lock: fails when another run published since this one was
    planned (its base is no longer current), so no run overwrites newer tiles.
    """
    job = Path(job_dir)
    spec = load_json(job / "job.json")
    s = spec["survey"]
    survey_dir = Path(s["dir"])
    root = product_root(survey_dir)
    summary_path = job / "outputs" / "survey.json"
    with _locked(root / ".lock"):
        if summary_path.exists():
            return load_json(summary_path)
        prev = current_version(survey_dir)
        new = root / f"v-{job.name}"
        if prev == new:  # switched, then stopped before the summary: done
            summary = _summary(survey_dir, new, s)
            write_json(summary_path, summary, indent=2)
            return summary
        if (None if prev is None else prev.name) != s["base"]:
            raise ProcessingError(
                "another run of this survey published since this run was planned; run it again"
            )
        shutil.rmtree(new, ignore_errors=True)
        present = []
        for name in s["tiles"]:
            stem = tile_stem(name)
            if name in s["outputs"]:
                src = _run_out(job, name)
            elif prev is not None and (prev / "tiles" / stem).is_dir():
                src = prev / "tiles" / stem
            else:
                continue  # added, and left for a later batch: not in the product yet
            _link_tree(src, new / "tiles" / stem, DERIVED)
            present.append(name)
        grid = BlockGrid(**s["grid"])
        pending = list(s.get("pending", []))
        (noise, slope_noise), derived = _derived_products(new, spec, grid, present, prev)
        state = {
            "version": new.name,
            "job": job.name,
            "tiles": {
                n: {
                    **{k: t[k] for k in ("path", "sha256", "size", "mtime_ns", "bounds", "window")},
                    "cells": list(window_bounds(grid, tuple(t["window"]))),
                }
                for n, t in s["tiles"].items()
            },
            "params_key": s["params_key"],
            "params": spec["params"],
            "density": s["density"],
            "anchor": s["anchor"],
            "grid_step": [grid.block_size, grid.resolution],
            # measured on a whole product only: a batch's DTM still lacks the pending tiles
            "noise": None if pending else noise,
            "slope_noise": None if pending else slope_noise,
            "pending": pending,
            "derived": derived,  # tiles whose slope and categories this version made again
        }
        write_json(new / STATE, state, indent=2)
        link = root / CURRENT
        tmp = root / f".{CURRENT}.{job.name}"
        if tmp.is_symlink():
            tmp.unlink()
        os.symlink(new.name, tmp)
        os.replace(tmp, link)  # the switch: readers see the old or the new version, whole
        for old in root.glob("v-*"):
            if old != new:
                shutil.rmtree(old, ignore_errors=True)
        summary = _summary(survey_dir, new, s)
        write_json(summary_path, summary, indent=2)
    return summary


def _summary(survey_dir: Path, version: Path, s: Mapping[str, Any]) -> dict[str, Any]:
    """What a run did: its product version, and the tiles it redid and read."""
    return {
        "survey": survey_dir.name,
        "version": version.name,
        "mode": s["mode"],
        "outputs": s["outputs"],
        "sources": s["sources"],
        "blocks": len(s["blocks"]),
        "pending": list(s.get("pending", [])),
        "derived": load_json(version / STATE).get("derived"),
    }


def _derived_products(
    new: Path, spec: Mapping[str, Any], grid: BlockGrid, present: list[str], prev: Path | None
) -> tuple[tuple[float, float], list[str]]:
    """VRTs, slope and categories per tile, merged features and the STAC collection of a
    version over its ``present`` tiles; returns the category noise and slope noise used
    (the survey's, else measured now) and the tiles whose slope and categories were made again (the
    others' are the previous version's files: their DTM within the margin is the same)."""
    import rasterio

    s = spec["survey"]
    params = spec["params"]
    tiles = {n: s["tiles"][n] for n in present}
    windows = {n: tuple(t["window"]) for n, t in tiles.items()}
    r0 = min(w[0] for w in windows.values())
    c0 = min(w[1] for w in windows.values())
    r1 = max(w[0] + w[2] for w in windows.values())
    c1 = max(w[1] + w[3] for w in windows.values())
    res = grid.resolution
    x_left, y_top = grid.x0 + c0 * res, grid.y_top - r0 * res
    crs = s["crs_wkt"]
    f = int(round(float(stage_params(params, "vegetation").cell) / res))

    def vrt(name: str, cell_cells: int, dtype: str, nodata: float | int, count: int = 1) -> None:
        srcs = [
            VrtSource(
                f"tiles/{tile_stem(n)}/{name}.tif",
                (w[1] - c0) // cell_cells,
                (w[0] - r0) // cell_cells,
                w[3] // cell_cells,
                w[2] // cell_cells,
            )
            for n, w in sorted(windows.items())
        ]
        cell = res * cell_cells
        write_vrt(
            new / f"{name}.vrt",
            srcs,
            width=(c1 - c0) // cell_cells,
            height=(r1 - r0) // cell_cells,
            geotransform=(x_left, cell, 0.0, y_top, 0.0, -cell),
            crs_wkt=crs,
            dtype=dtype,
            nodata=nodata,
            count=count,
            descriptions=band_metadata(name).get("descriptions"),
        )

    for r in ("dtm", "dsm", "chm"):
        vrt(r, 1, "float32", FLOAT_NODATA)
    vrt("coverage", f, "uint8", COVERAGE_NODATA)

    from rasterio.windows import Window as RWindow

    from terrasift.jobs.finish import BAND_CELLS, _read_rows
    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat
    from terrasift.workers import terrain
    from terrasift.workers.features import tiled

    tparams = stage_params(params, "terrain")
    cparams = stage_params(params, "categories")
    if cparams.noise is None and s.get("noise") is not None:
        cparams = cparams.model_copy(update={"noise": s["noise"]})
    if cparams.slope_noise is None and s.get("slope_noise") is not None:
        cparams = cparams.model_copy(update={"slope_noise": s["slope_noise"]})
    filters = feat.resolve_filters(params.get("features", "all"), params.get("filters") or {})
    fparams = stage_params(params, "features")
    m = tparams.median_size // 2 + 2  # slope's smoothing margin, in cells
    work = new / ".work"
    work.mkdir()
    pieces: list = []
    with bounded_raster_cache(), rasterio.open(new / "dtm.vrt") as ds:
        height, width = ds.height, ds.width
        transform = ds.transform
        if cparams.noise is None:  # measured on the whole DTM, streamed in bands
            rows_per_band = max(1, BAND_CELLS // width)
            cparams = cparams.model_copy(
                update={
                    "noise": cat.measure_noise_by_bands(
                        lambda a, b: _read_rows(ds, a, b), height, res, cparams, rows_per_band
                    )
                }
            )
        if cparams.slope_noise is None:  # likewise
            rows_per_band = max(1, BAND_CELLS // width)
            cparams = cparams.model_copy(
                update={
                    "slope_noise": 0.0
                    if cparams.noise == 0
                    else cat.measure_slope_noise_by_bands(
                        lambda a, b: _read_rows(ds, a, b), height, res, cparams, rows_per_band
                    )
                }
            )
        noise, slope_noise = float(cparams.noise), float(cparams.slope_noise)
        stale = _stale_derived(
            prev, grid, windows, set(s["outputs"]), (m + 1) * res, noise, slope_noise
        )

        def read(lo_r: int, hi_r: int, lo_c: int, hi_c: int) -> np.ndarray:
            return (
                ds.read(1, window=RWindow(lo_c, lo_r, hi_c - lo_c, hi_r - lo_r), masked=True)
                .filled(np.nan)
                .astype(np.float64)
            )

        kc = max(2, int(round(cparams.tile_size / res)))
        for n, (wr, wc, rows, cols) in windows.items():
            target = new / "tiles" / tile_stem(n)
            if n not in stale:  # its DTM within the margin is unchanged: so are these
                for kept in ("slope.tif", "categories.tif"):
                    os.link(prev / "tiles" / tile_stem(n) / kept, target / kept)  # type: ignore[operator]
                continue
            xmin, _, _, ymax = window_bounds(grid, (wr, wc, rows, cols))
            # slope read with a margin for its smoothing: equal to slope over the mosaic
            rr, cc = wr - r0, wc - c0
            lo_r, hi_r = max(0, rr - m), min(height, rr + rows + m)
            lo_c, hi_c = max(0, cc - m), min(width, cc + cols + m)
            slope = terrain.slope_degrees(
                read(lo_r, hi_r, lo_c, hi_c), res, tparams.median_size, tparams.smooth
            )
            sm = RasterMosaic(
                work / f"{tile_stem(n)}-slope.tif",
                width=cols,
                height=rows,
                transform=job_transform(xmin, ymax, res),
                crs=crs,
                **band_metadata("slope"),
            )
            sm.write(0, 0, slope[rr - lo_r : rr - lo_r + rows, cc - lo_c : cc - lo_c + cols])
            sm.close_as_cog(target / "slope.tif")
            # categories from the tile's own cells: a category tile (aligned to the tile's
            # window) reads only its cells, and the noise is the survey's
            part = cat.category_grids(read(rr, rr + rows, cc, cc + cols), res, cparams)[0].bands()
            cm = RasterMosaic(
                work / f"{tile_stem(n)}-categories.tif",
                width=part.shape[2],
                height=part.shape[1],
                transform=job_transform(xmin, ymax, res * kc),
                crs=crs,
                dtype="uint8",
                nodata=cat.NODATA,
                count=4,
                **band_metadata("categories"),
            )
            cm.write(0, 0, part)
            cm.close_as_cog(target / "categories.tif", resampling="nearest")
        # Features core by core (squares of FEATURE_CORE_M): each core's search reads the
        # core and a halo and keeps the objects whose first category tile it holds
        # (tiled.py), so memory follows a core and an object across core edges comes out once.
        if filters:
            side = max(1, int(round(FEATURE_CORE_M / res)))
            spans = [
                (wr - r0, wc - c0, wr - r0 + rows, wc - c0 + cols)
                for wr, wc, rows, cols in windows.values()
            ]
            for i in range(0, height, side):
                for j in range(0, width, side):
                    core = (i, j, min(height, i + side), min(width, j + side))
                    if any(_overlaps_cells(core, w) for w in spans):
                        pieces += tiled.tile_pieces(
                            read, (height, width), transform, core, filters, cparams, fparams
                        )
    vrt("slope", 1, "float32", FLOAT_NODATA)
    vrt("categories", kc, "uint8", cat.NODATA, count=4)
    if filters:  # the tiles' pieces joined, sized and limited as over the whole survey
        result = tiled.merge_pieces(pieces, filters, cparams, res, fparams)
        from terrasift.tiling.vectors import crs_member

        survey_id = Path(s["dir"]).name
        native = feat.features_geojson(result, crs or 0, survey_id, to_wgs84=False)
        member = crs_member(crs)
        write_json(
            new / "features.native.geojson", {**native, **({"crs": member} if member else {})}
        )
        if crs:
            write_json(
                new / "features.geojson",
                feat.features_geojson(result, crs, survey_id, to_wgs84=True),
            )
    shutil.rmtree(work, ignore_errors=True)
    _write_stac(new, s, tiles)
    return (noise, slope_noise), sorted(stale)


def _overlaps_cells(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Two windows of cells (row0, col0, row1, col1; ends excluded) share a cell."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _stale_derived(
    prev: Path | None,
    grid: BlockGrid,
    windows: Mapping[str, Window],
    outputs: set[str],
    margin: float,
    noise: float,
    slope_noise: float,
) -> set[str]:
    """Tiles whose slope and categories must be made again: those within ``margin``
    (metres) of cells that changed (a redone tile, a tile gone, a tile whose cells
    moved), all of them when a noise or the grid changed or there is no product."""
    state = load_json(prev / STATE) if prev is not None and (prev / STATE).exists() else {}
    cells = {n: window_bounds(grid, w) for n, w in windows.items()}
    if not state or state.get("noise") != noise or state.get("slope_noise") != slope_noise:
        return set(windows)
    old = state.get("tiles", {})
    changed = [cells[n] for n in windows if n in outputs]
    for n, t in old.items():
        was = tuple(t["cells"]) if t.get("cells") else None
        if n not in windows or was != cells[n]:
            changed += [b for b in (was, cells.get(n)) if b is not None]
    stale = set()
    for n, b in cells.items():
        wide = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
        files = [prev / "tiles" / tile_stem(n) / f for f in ("slope.tif", "categories.tif")]  # type: ignore[operator]
        if not all(f.exists() for f in files) or any(_overlaps(wide, r) for r in changed):
            stale.add(n)
    return stale


def _write_stac(new: Path, s: Mapping[str, Any], tiles: Mapping[str, Any]) -> None:
    """One STAC Item per tile (its files) and a Collection linking them."""
    from terrasift.tiling.stac import STAC_VERSION, stac_item

    survey_id = Path(s["dir"]).name
    crs_wkt = s["crs_wkt"]
    links: list[dict[str, Any]] = []
    boxes = []
    for n, t in sorted(tiles.items()):
        d = new / "tiles" / tile_stem(n)
        names = sorted(p.name for p in d.iterdir() if p.is_file() and p.name != "item.json")
        item = stac_item(
            tile_stem(n),
            d,
            {"tiles": [{"path": t["path"]}], "crs_wkt": crs_wkt, "crs": _crs_label(crs_wkt)},
            names,
        )
        item["collection"] = survey_id
        item["links"] = [
            {"rel": "self", "href": "./item.json", "type": "application/geo+json"},
            {"rel": "parent", "href": "../../collection.json", "type": "application/json"},
            {"rel": "collection", "href": "../../collection.json", "type": "application/json"},
            {"rel": "root", "href": "../../collection.json", "type": "application/json"},
        ]
        write_json(d / "item.json", item, indent=2)
        if "bbox" in item:
            boxes.append(item["bbox"])
        links.append(
            {
                "rel": "item",
                "href": f"./tiles/{tile_stem(n)}/item.json",
                "type": "application/geo+json",
            }
        )
    bbox = (
        [
            min(b[0] for b in boxes),
            min(b[1] for b in boxes),
            max(b[2] for b in boxes),
            max(b[3] for b in boxes),
        ]
        if boxes
        else [-180.0, -90.0, 180.0, 90.0]
    )
    collection = {
        "type": "Collection",
        "stac_version": STAC_VERSION,
        "id": survey_id,
        "description": f"terrasift survey {survey_id}: one item per tile",
        "license": "other",
        "extent": {"spatial": {"bbox": [bbox]}, "temporal": {"interval": [[None, None]]}},
        "links": [
            {"rel": "self", "href": "./collection.json", "type": "application/json"},
            {"rel": "root", "href": "./collection.json", "type": "application/json"},
            *links,
        ],
    }
    write_json(new / "collection.json", collection, indent=2)


def product_files(version: Path) -> list[str]:
    """Every file of a product version, relative to it, mosaics first."""
    top = [f"{m}.vrt" for m in MOSAICS if (version / f"{m}.vrt").exists()]
    top += [
        n
        for n in ("features.geojson", "features.native.geojson", "collection.json")
        if (version / n).exists()
    ]
    tiles = sorted(
        str(p.relative_to(version)) for p in (version / "tiles").rglob("*") if p.is_file()
    )
    return top + tiles
