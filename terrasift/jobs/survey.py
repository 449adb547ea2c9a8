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
the new version. Derived products are tasks of their own, run in parallel
once the run's DTMs are written (``stage_derived`` decides which): slope and
categories (with the survey's fixed noise) per tile from the new DTM mosaic,
only for tiles within the slope's margin of changed cells; features per square
of ``FEATURE_CORE_M`` with a halo (an object may cross any number of tile
edges: the search grows around it, ``workers/features/tiled.py``), only for
squares whose searched window holds a changed cell, the others' pieces kept
from the previous version. The publish joins the pieces into objects.

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
from terrasift.jobs.plan import _crs_label, resolve_crs
from terrasift.tiling.blocks import BlockGrid, block_name
from terrasift.tiling.classified import write_classified_copy
from terrasift.tiling.lasfile import read_tile_info
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
#: and its halo, not the survey. 320 m keeps a square and its halo under ~0.9 km, so a
#: survey of that width already reaches the bound; wider squares redo less of their halo
FEATURE_CORE_M = 320.0
#: a version's hidden folder of each feature square's pieces, reused while no cell of
#: the window the square searched changes
SQUARES = ".squares"
#: halo (metres) each square's search starts with; None: the filters' reach and 32 m.
#: Any halo gives the same objects (the search grows around an object that needs it);
#: a smaller one reads less up front and grows more often
FEATURE_HALO_M: float | None = None
#: metres a square's window may grow beyond its halo (``tiled.search_core``'s cap): an
#: object larger than that (a level plain, a road across the survey) is searched in
#: parts, square by square, and joined from them, so no window passes a square, its
#: halo and this; None: windows grow around whole objects. ``TERRASIFT_FEATURE_CAP_M``
#: (metres, or ``none``) sets it in the processes that run the squares' tasks
FEATURE_CAP_M: float | None = 256.0
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
    infos = {n: read_tile_info(p, max_points=max_points) for n, p in by_name.items()}
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
    infos = [read_tile_info(p) for p in job["inputs"]]
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
        _check_base(s, prev)
        shutil.rmtree(new, ignore_errors=True)
        for name in load_json(_derived_dir(job) / "stage.json")["present"]:
            stem = tile_stem(name)
            src = _run_out(job, name) if name in s["outputs"] else prev / "tiles" / stem  # type: ignore[operator]
            _link_tree(src, new / "tiles" / stem, DERIVED)
        grid = BlockGrid(**s["grid"])
        pending = list(s.get("pending", []))
        made = _assemble(job, new, spec, grid, prev)
        noise, slope_noise = made["noise"], made["slope_noise"]
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
            "derived": made["derived"],  # tiles whose slope and categories were made again
            "squares": made["squares"],  # feature squares: windows searched, searched again
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
    state = load_json(version / STATE)
    return {
        "survey": survey_dir.name,
        "version": version.name,
        "mode": s["mode"],
        "outputs": s["outputs"],
        "sources": s["sources"],
        "blocks": len(s["blocks"]),
        "pending": list(s.get("pending", [])),
        "derived": state.get("derived"),
        # feature squares of the product, and those this run searched again
        "squares": len((state.get("squares") or {}).get("windows", {})),
        "squares_searched": (state.get("squares") or {}).get("searched"),
    }


def _derived_dir(job: Path) -> Path:
    """Where a run's derived products (slope, categories, feature squares) are made."""
    return job / "work" / "derived"


def _extent(windows: Mapping[str, Window]) -> tuple[int, int, int, int]:
    """Survey-grid cells (row0, col0, row1, col1) of the mosaic over ``windows``."""
    return (
        min(w[0] for w in windows.values()),
        min(w[1] for w in windows.values()),
        max(w[0] + w[2] for w in windows.values()),
        max(w[1] + w[3] for w in windows.values()),
    )


def _write_mosaic(
    path: Path,
    name: str,
    grid: BlockGrid,
    crs: str | None,
    windows: Mapping[str, Window],
    hrefs: Mapping[str, str],
    cell_cells: int,
    dtype: str,
    nodata: float | int,
    count: int = 1,
) -> None:
    """A VRT over the tiles' rasters ``hrefs`` (relative to the VRT) at their ``windows``."""
    r0, c0, r1, c1 = _extent(windows)
    res = grid.resolution
    srcs = [
        VrtSource(
            hrefs[n],
            (w[1] - c0) // cell_cells,
            (w[0] - r0) // cell_cells,
            w[3] // cell_cells,
            w[2] // cell_cells,
        )
        for n, w in sorted(windows.items())
    ]
    cell = res * cell_cells
    write_vrt(
        path,
        srcs,
        width=(c1 - c0) // cell_cells,
        height=(r1 - r0) // cell_cells,
        geotransform=(grid.x0 + c0 * res, cell, 0.0, grid.y_top - r0 * res, 0.0, -cell),
        crs_wkt=crs,
        dtype=dtype,
        nodata=nodata,
        count=count,
        descriptions=band_metadata(name).get("descriptions"),
    )


def _present(job: Path, s: Mapping[str, Any], prev: Path | None) -> list[str]:
    """Tiles of the new version: the run's outputs and the previous version's others
    (a tile added and left pending for a later batch is not in the product yet)."""
    return [
        n
        for n in s["tiles"]
        if n in s["outputs"] or (prev is not None and (prev / "tiles" / tile_stem(n)).is_dir())
    ]


def _check_base(s: Mapping[str, Any], prev: Path | None) -> None:
    if (None if prev is None else prev.name) != s["base"]:
        raise ProcessingError(
            "another run of this survey published since this run was planned; run it again"
        )


def _derived_params(
    spec: Mapping[str, Any], noise: float | None = None, slope_noise: float | None = None
) -> dict[str, Any]:
    from terrasift.workers import features as feat

    params = spec["params"]
    cparams = stage_params(params, "categories")
    if noise is not None and cparams.noise is None:
        cparams = cparams.model_copy(update={"noise": noise})
    if slope_noise is not None and cparams.slope_noise is None:
        cparams = cparams.model_copy(update={"slope_noise": slope_noise})
    return {
        "terrain": stage_params(params, "terrain"),
        "categories": cparams,
        "features": stage_params(params, "features"),
        "filters": feat.resolve_filters(params.get("features", "all"), params.get("filters") or {}),
    }


def feature_cap_m() -> float | None:
    """The feature squares' cap in metres: ``TERRASIFT_FEATURE_CAP_M`` if set, else
    ``FEATURE_CAP_M``."""
    env = os.environ.get("TERRASIFT_FEATURE_CAP_M", "").strip().lower()
    if not env:
        return FEATURE_CAP_M
    if env == "none":
        return None
    value = float(env)
    if not value >= 0:
        raise ValueError(f"TERRASIFT_FEATURE_CAP_M must be metres >= 0 or none, not {env!r}")
    return value


def stage_derived(job_dir: str) -> dict[str, Any]:
    """Task: what the run's derived products need, once its tiles' DTMs are written.

    Writes ``work/derived/dtm.vrt`` (the new version's DTM mosaic: this run's tiles
    and the previous version's others) and ``stage.json``: the tiles of the new
    version, the category noise and slope noise (the survey's, else measured on that
    mosaic), the
    tiles whose slope and categories must be made again (those near changed cells)
    and the feature squares (``FEATURE_CORE_M``) to search again (those whose
    searched window holds a changed cell; the others' pieces are the previous
    version's). Each of those is then a task of its own.
    """
    job = Path(job_dir)
    d = _derived_dir(job)
    if (d / "stage.json").exists():
        return load_json(d / "stage.json")
    if (job / "outputs" / "survey.json").exists():  # published already: nothing to make
        return {"tiles": [], "search": []}
    spec = load_json(job / "job.json")
    s = spec["survey"]
    prev = current_version(Path(s["dir"]))
    _check_base(s, prev)
    grid = BlockGrid(**s["grid"])
    res = grid.resolution
    present = _present(job, s, prev)
    windows = {n: tuple(s["tiles"][n]["window"]) for n in present}
    d.mkdir(parents=True, exist_ok=True)
    dtms = {
        n: (_run_out(job, n) if n in s["outputs"] else prev / "tiles" / tile_stem(n))  # type: ignore[operator]
        / "dtm.tif"
        for n in present
    }
    hrefs = {n: os.path.relpath(p, d) for n, p in dtms.items()}
    _write_mosaic(
        d / "dtm.vrt", "dtm", grid, s["crs_wkt"], windows, hrefs, 1, "float32", FLOAT_NODATA
    )
    p = _derived_params(spec, s.get("noise"), s.get("slope_noise"))
    cparams = p["categories"]
    if cparams.noise is None or cparams.slope_noise is None:  # measured on the whole DTM
        import rasterio

        from terrasift.jobs.finish import BAND_CELLS, _read_rows
        from terrasift.workers import categories as cat

        with bounded_raster_cache(), rasterio.open(d / "dtm.vrt") as ds:
            rows = max(1, BAND_CELLS // ds.width)
            if cparams.noise is None:
                cparams = cparams.model_copy(
                    update={
                        "noise": cat.measure_noise_by_bands(
                            lambda a, b: _read_rows(ds, a, b), ds.height, res, cparams, rows
                        )
                    }
                )
            if cparams.slope_noise is None:  # against the noise just fixed
                cparams = cparams.model_copy(
                    update={
                        "slope_noise": 0.0
                        if cparams.noise == 0
                        else cat.measure_slope_noise_by_bands(
                            lambda a, b: _read_rows(ds, a, b), ds.height, res, cparams, rows
                        )
                    }
                )
    noise, slope_noise = float(cparams.noise), float(cparams.slope_noise)
    m = p["terrain"].median_size // 2 + 2  # slope's smoothing margin, in cells
    stale = _stale_derived(
        prev, grid, windows, set(s["outputs"]), (m + 1) * res, (noise, slope_noise)
    )
    extent = _extent(windows)
    side = max(1, int(round(FEATURE_CORE_M / res)))
    squares: dict[str, list[int]] = {}
    if any(f.connect is not None or f.rectangle is not None for f in p["filters"]):
        spans = [
            (w[0] - extent[0], w[1] - extent[1], w[0] - extent[0] + w[2], w[1] - extent[1] + w[3])
            for w in windows.values()
        ]
        from terrasift.jobs.finish import feature_squares

        height, width = extent[2] - extent[0], extent[3] - extent[1]
        squares = {k: list(v) for k, v in feature_squares(height, width, side, spans).items()}
    cap_m = feature_cap_m()
    cap = None if cap_m is None else int(round(cap_m / res))
    search = _stale_squares(
        prev, grid, windows, set(s["outputs"]), (noise, slope_noise), extent, side, squares, cap
    )
    stage = {
        "base": s["base"],
        "present": present,
        "noise": noise,
        "slope_noise": slope_noise,
        "tiles": sorted(stale),
        "extent": list(extent),
        "side": side,
        "cap": cap,
        "squares": squares,
        "search": sorted(search),
    }
    write_json(d / "stage.json", stage, indent=2)
    return stage


def write_tile_derived(job_dir: str, name: str) -> str:
    """Task: tile ``name``'s slope and categories COGs from the new DTM mosaic.

    Slope reads the tile with a margin for its smoothing (so it equals slope over
    the mosaic); categories read the tile's own cells (category tiles are aligned to
    the tile's window) with the survey's noise.
    """
    import rasterio
    from rasterio.windows import Window as RWindow

    from terrasift.workers import categories as cat
    from terrasift.workers import terrain

    job = Path(job_dir)
    d = _derived_dir(job)
    out = d / "tiles" / tile_stem(name)
    if (out / "slope.tif").exists() and (out / "categories.tif").exists():
        return name
    spec = load_json(job / "job.json")
    s = spec["survey"]
    stage = load_json(d / "stage.json")
    grid = BlockGrid(**s["grid"])
    res = grid.resolution
    p = _derived_params(spec, stage["noise"], stage["slope_noise"])
    tparams, cparams = p["terrain"], p["categories"]
    r0, c0 = stage["extent"][:2]
    wr, wc, rows, cols = s["tiles"][name]["window"]
    xmin, _, _, ymax = window_bounds(grid, (wr, wc, rows, cols))
    m = tparams.median_size // 2 + 2
    kc = max(2, int(round(cparams.tile_size / res)))
    work = job / "work" / "tiles"
    work.mkdir(parents=True, exist_ok=True)
    stem = tile_stem(name)
    with bounded_raster_cache(), rasterio.open(d / "dtm.vrt") as ds:

        def read(lo_r: int, hi_r: int, lo_c: int, hi_c: int) -> np.ndarray:
            return (
                ds.read(1, window=RWindow(lo_c, lo_r, hi_c - lo_c, hi_r - lo_r), masked=True)
                .filled(np.nan)
                .astype(np.float64)
            )

        rr, cc = wr - r0, wc - c0
        lo_r, hi_r = max(0, rr - m), min(ds.height, rr + rows + m)
        lo_c, hi_c = max(0, cc - m), min(ds.width, cc + cols + m)
        slope = terrain.slope_degrees(
            read(lo_r, hi_r, lo_c, hi_c), res, tparams.median_size, tparams.smooth
        )
        sm = RasterMosaic(
            work / f"{stem}-slope.tif",
            width=cols,
            height=rows,
            transform=job_transform(xmin, ymax, res),
            crs=s["crs_wkt"],
            **band_metadata("slope"),
        )
        sm.write(0, 0, slope[rr - lo_r : rr - lo_r + rows, cc - lo_c : cc - lo_c + cols])
        sm.close_as_cog(out / "slope.tif")
        part = cat.category_grids(read(rr, rr + rows, cc, cc + cols), res, cparams)[0].bands()
        cm = RasterMosaic(
            work / f"{stem}-categories.tif",
            width=part.shape[2],
            height=part.shape[1],
            transform=job_transform(xmin, ymax, res * kc),
            crs=s["crs_wkt"],
            dtype="uint8",
            nodata=cat.NODATA,
            count=4,
            **band_metadata("categories"),
        )
        cm.write(0, 0, part)
        cm.close_as_cog(out / "categories.tif", resampling="nearest")
    return name


def search_feature_square(job_dir: str, key: str) -> str:
    """Task: the feature pieces square ``key`` owns, searched on the square and a halo of
    the new DTM mosaic (``tiled.search_core``); saved with the window searched."""
    import pickle

    import rasterio
    from rasterio.windows import Window as RWindow

    from terrasift.files import atomic_path
    from terrasift.workers.features import tiled

    job = Path(job_dir)
    d = _derived_dir(job)
    path = d / "squares" / f"{key}.pkl"
    if path.exists():
        return key
    spec = load_json(job / "job.json")
    stage = load_json(d / "stage.json")
    p = _derived_params(spec, stage["noise"], stage["slope_noise"])
    core = tuple(stage["squares"][key])
    with bounded_raster_cache(), rasterio.open(d / "dtm.vrt") as ds:

        def read(lo_r: int, hi_r: int, lo_c: int, hi_c: int) -> np.ndarray:
            return (
                ds.read(1, window=RWindow(lo_c, lo_r, hi_c - lo_c, hi_r - lo_r), masked=True)
                .filled(np.nan)
                .astype(np.float64)
            )

        pieces, window = tiled.search_core(
            read,
            (ds.height, ds.width),
            ds.transform,
            core,
            p["filters"],
            p["categories"],
            p["features"],
            None if FEATURE_HALO_M is None else int(round(FEATURE_HALO_M / abs(ds.transform.a))),
            stage.get("cap"),
        )
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(pickle.dumps({"pieces": pieces, "window": list(window)}))
    return key


def _assemble(
    job: Path, new: Path, spec: Mapping[str, Any], grid: BlockGrid, prev: Path | None
) -> dict[str, Any]:
    """VRTs, the tiles' slope and categories, merged features and the STAC collection of
    a version from the run's derived products (``stage_derived`` and the tasks after it)
    and the previous version's files for the rest; what ``state.json`` records of them."""
    import pickle

    import rasterio

    from terrasift.jobs.finish import dtm_heights
    from terrasift.workers import categories as cat
    from terrasift.workers import features as feat
    from terrasift.workers.features import tiled

    s = spec["survey"]
    d = _derived_dir(job)
    stage = load_json(d / "stage.json")
    present = stage["present"]
    tiles = {n: s["tiles"][n] for n in present}
    windows = {n: tuple(t["window"]) for n, t in tiles.items()}
    res = grid.resolution
    crs = s["crs_wkt"]
    p = _derived_params(spec, stage["noise"], stage["slope_noise"])
    f = int(round(float(stage_params(spec["params"], "vegetation").cell) / res))
    kc = max(2, int(round(p["categories"].tile_size / res)))
    remade = set(stage["tiles"])
    for n in present:
        target = new / "tiles" / tile_stem(n)
        src = d / "tiles" / tile_stem(n) if n in remade else prev / "tiles" / tile_stem(n)  # type: ignore[operator]
        for kept in ("slope.tif", "categories.tif"):
            os.link(src / kept, target / kept)
    for name, cells, dtype, nodata, count in (
        ("dtm", 1, "float32", FLOAT_NODATA, 1),
        ("dsm", 1, "float32", FLOAT_NODATA, 1),
        ("chm", 1, "float32", FLOAT_NODATA, 1),
        ("coverage", f, "uint8", COVERAGE_NODATA, 1),
        ("slope", 1, "float32", FLOAT_NODATA, 1),
        ("categories", kc, "uint8", cat.NODATA, 4),
    ):
        hrefs = {n: f"tiles/{tile_stem(n)}/{name}.tif" for n in present}
        _write_mosaic(
            new / f"{name}.vrt",
            name,
            grid,
            crs,
            windows,
            hrefs,
            cells,
            dtype,
            nodata,
            count,
        )
    # each square's pieces: searched by this run, or the previous version's (no cell of
    # the window it searched changed); joined, sized and limited as over the whole survey
    searched = set(stage["search"])
    windows_searched: dict[str, list[int]] = {}
    pieces: list = []
    if stage["squares"]:
        (new / SQUARES).mkdir()
    for key in sorted(stage["squares"]):
        src = d / "squares" / f"{key}.pkl" if key in searched else prev / SQUARES / f"{key}.pkl"  # type: ignore[operator]
        os.link(src, new / SQUARES / f"{key}.pkl")
        found = pickle.loads(src.read_bytes())
        pieces += found["pieces"]
        windows_searched[key] = found["window"]
    if p["filters"]:
        with bounded_raster_cache(), rasterio.open(d / "dtm.vrt") as ds:  # the searched DTM
            result = tiled.merge_pieces(
                pieces, p["filters"], p["categories"], res, p["features"], dtm=dtm_heights(ds)
            )
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
    _write_stac(new, s, tiles)
    return {
        "noise": stage["noise"],
        "slope_noise": stage["slope_noise"],
        "derived": stage["tiles"],
        "squares": {
            "extent": stage["extent"],
            "side": stage["side"],
            "cap": stage.get("cap"),
            "windows": windows_searched,
            "searched": stage["search"],
        },
    }


def _overlaps_cells(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Two windows of cells (row0, col0, row1, col1; ends excluded) share a cell."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _changed(
    prev: Path | None,
    grid: BlockGrid,
    windows: Mapping[str, Window],
    outputs: set[str],
    noises: tuple[float, float],
) -> list[Bounds] | None:
    """Where cells changed since the previous version (a redone tile, a tile gone, a
    tile whose cells moved), in metres; None when everything must be made again (no
    product, or a noise (category, slope) or the grid changed)."""
    state = load_json(prev / STATE) if prev is not None and (prev / STATE).exists() else {}
    if not state or (state.get("noise"), state.get("slope_noise")) != noises:
        return None
    cells = {n: window_bounds(grid, w) for n, w in windows.items()}
    changed = [cells[n] for n in windows if n in outputs]
    for n, t in state.get("tiles", {}).items():
        was = tuple(t["cells"]) if t.get("cells") else None
        if n not in windows or was != cells[n]:
            changed += [b for b in (was, cells.get(n)) if b is not None]
    return changed


def _stale_derived(
    prev: Path | None,
    grid: BlockGrid,
    windows: Mapping[str, Window],
    outputs: set[str],
    margin: float,
    noises: tuple[float, float],
) -> set[str]:
    """Tiles whose slope and categories must be made again: those within ``margin``
    (metres) of cells that changed, all of them when a noise or the grid changed or
    there is no product."""
    changed = _changed(prev, grid, windows, outputs, noises)
    if changed is None:
        return set(windows)
    stale = set()
    for n, w in windows.items():
        b = window_bounds(grid, w)
        wide = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
        files = [prev / "tiles" / tile_stem(n) / f for f in ("slope.tif", "categories.tif")]  # type: ignore[operator]
        if not all(f.exists() for f in files) or any(_overlaps(wide, r) for r in changed):
            stale.add(n)
    return stale


def _stale_squares(
    prev: Path | None,
    grid: BlockGrid,
    windows: Mapping[str, Window],
    outputs: set[str],
    noises: tuple[float, float],
    extent: tuple[int, int, int, int],
    side: int,
    squares: Mapping[str, list[int]],
    cap: int | None = None,
) -> set[str]:
    """Feature squares to search again: those whose window searched last time holds a
    changed cell (or reaches past a cut edge); all when the mosaic's extent, the
    squares, their cap or a noise changed. A square's pieces depend only on the DTM
    cells of the window its search read (``tiled.search_core``), so the others' are
    the same."""
    changed = _changed(prev, grid, windows, outputs, noises)
    if changed is None:
        return set(squares)
    old = load_json(prev / STATE).get("squares") or {}  # type: ignore[operator]
    if old.get("extent") != list(extent) or old.get("side") != side or old.get("cap") != cap:
        return set(squares)
    res = grid.resolution
    r0, c0 = extent[0], extent[1]
    x_left, y_top = grid.x0 + c0 * res, grid.y_top - r0 * res
    cells = [
        (
            int(round((y_top - b[3]) / res)),
            int(round((b[0] - x_left) / res)),
            int(round((y_top - b[1]) / res)),
            int(round((b[2] - x_left) / res)),
        )
        for b in changed
    ]
    seen = old.get("windows", {})
    return {
        k
        for k in squares
        if k not in seen
        or not (prev / SQUARES / f"{k}.pkl").exists()  # type: ignore[operator]
        or any(_overlaps_cells(tuple(seen[k]), c) for c in cells)
    }


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
