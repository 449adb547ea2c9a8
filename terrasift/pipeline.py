"""A job from inputs to outputs: plan, shard, blocks, finish — resumable at every step.

The job directory holds everything: ``job.json`` (inputs, parameters),
``plan.json`` (tiles, CRS, block grid), ``shards/<tile>/<block>.bin``,
``blocks/<block>.npz`` and ``outputs/``. Each task writes its result
atomically and is skipped when the result exists, so a restarted service or
a repeated ``process`` call redoes only what is missing. The CLI and the
service both drive jobs through ``run_job``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from terrasift.errors import InputError, JobCancelled, ProcessingError
from terrasift.params import grid_alignment, resolve_buffer, validate_params
from terrasift.tiling.blocks import BlockGrid, shard_parts, shard_tile
from terrasift.tiling.lasfile import TileInfo, read_tile_info
from terrasift.workers.block import run_block
from terrasift.workers.executors import Executor, Future

__all__ = [
    "validate_params",
    "inspect_inputs",
    "prepare_job",
    "run_job",
    "request_cancel",
    "check_cancel",
    "output_path",
]

log = logging.getLogger(__name__)
CANCEL_MARKER = "CANCELLED"
Progress = Callable[[int, int], None]


# ------------------------------------------------------------------ helpers


def load_json(path: Path) -> Any:
    return json.loads(Path(path).read_text())


def write_json_atomic(path: Path, data: Any) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str))
    os.replace(tmp, path)


def output_path(job_dir: Path, name: str) -> Path:
    """Where output ``name`` of a job lives (it may not exist yet)."""
    return Path(job_dir) / "outputs" / name


def request_cancel(job_dir: Path) -> None:
    """Mark the job dismissed; running tasks stop at their next stage boundary."""
    Path(job_dir).mkdir(parents=True, exist_ok=True)
    (Path(job_dir) / CANCEL_MARKER).touch()


def is_cancelled(job_dir: Path) -> bool:
    return (Path(job_dir) / CANCEL_MARKER).exists()


def check_cancel(job_dir: Path) -> None:
    if is_cancelled(job_dir):
        raise JobCancelled("job was dismissed")


# ------------------------------------------------------------------ submission


def inspect_inputs(
    paths: list[Path], params: Mapping[str, Any], *, max_points: int | None = None
) -> dict[str, Any]:
    """Check every input's header (no points read) and the job's CRS.

    Raises InputError naming the problem. Returns a summary for the job record.
    """
    if not paths:
        raise InputError("no input files")
    infos = [read_tile_info(p, max_points=max_points) for p in paths]
    crs_wkt, warnings = resolve_crs(infos, params.get("crs"))
    mins = [min(i.mins[k] for i in infos) for k in range(3)]
    maxs = [max(i.maxs[k] for i in infos) for k in range(3)]
    return {
        "tiles": len(infos),
        "points": sum(i.point_count for i in infos),
        "bounds": [*mins, *maxs],
        "crs": _crs_label(crs_wkt),
        "warnings": warnings,
    }


def resolve_crs(infos: list[TileInfo], override: str | None) -> tuple[str | None, list[str]]:
    """The job's CRS as WKT: the ``crs`` parameter, else the tiles' common CRS."""
    warnings = [w for i in infos for w in i.warnings]
    if override:
        crs = pyproj.CRS.from_user_input(override)
        return crs.to_wkt(), [w for w in warnings if "no CRS" not in w]
    found = [pyproj.CRS.from_wkt(i.crs_wkt) for i in infos if i.crs_wkt]
    if not found:
        warnings.append(
            "no CRS known: rasters carry none and features.geojson is not written; pass crs=EPSG:..."
        )
        return None, warnings
    first = found[0]
    for other, info in zip(found[1:], [i for i in infos if i.crs_wkt][1:], strict=True):
        if not first.equals(other, ignore_axis_order=True):
            raise InputError(
                f"tiles of one job must share a CRS: {Path(info.path).name} is {_crs_label(other.to_wkt())}, "
                f"the first tile is {_crs_label(first.to_wkt())}"
            )
    if len(found) < len(infos):
        warnings.append("some tiles have no CRS; the others' CRS is used for all")
    return first.to_wkt(), warnings


def _crs_label(wkt: str | None) -> str | None:
    if not wkt:
        return None
    crs = pyproj.CRS.from_wkt(wkt)
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else crs.name


def prepare_job(job_dir: Path, inputs: list[Path], params: Mapping[str, Any]) -> None:
    """Write the job's ``job.json`` (inputs as absolute paths, validated parameters)."""
    job_dir = Path(job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(
        job_dir / "job.json",
        {"inputs": [str(Path(p).resolve()) for p in inputs], "params": dict(params)},
    )


# ------------------------------------------------------------------ running


def run_job(
    job_dir: Path, executor: Executor, progress: Progress | None = None, *, products: str = "all"
) -> list[str]:
    """Run (or resume) the job in ``job_dir`` on ``executor``; return output names.

    ``products="classified"`` writes only the classified point clouds (and the report).
    """
    job_dir = Path(job_dir)
    progress = progress or (lambda done, total: None)
    started = time.perf_counter()
    check_cancel(job_dir)
    job = load_json(job_dir / "job.json")
    params = job["params"]
    plan = _plan(job_dir, job)
    grid = BlockGrid(**plan["grid"])
    n_tiles = len(plan["tiles"])

    from terrasift.tiling import outputs

    # Finishing tasks: one classified point cloud per tile, and (all products)
    # the rasters, then slope/categories/features from the mosaicked DTM. The
    # list is in order of priority: the DTM first, since the terrain tasks
    # wait on it, then the long tasks, so the workers finish together.
    finish: list[Task] = [Task(outputs.write_classified, (str(job_dir), i)) for i in range(n_tiles)]
    if products == "all":
        dtm = Task(outputs.write_raster, (str(job_dir), "dtm"))
        terrain = [
            Task(fn, (str(job_dir),), after=(0,))
            for fn in (outputs.write_categories, outputs.write_slope)
        ]
        others = [
            Task(outputs.write_raster, (str(job_dir), n)) for n in outputs.RASTERS if n != "dtm"
        ]
        finish = [dtm, *finish, *terrain, *others]

    # Progress counts tasks: shards, blocks, finishing tasks, the report.
    shard_root = job_dir / "shards"
    parts = shard_parts([t["point_count"] for t in plan["tiles"]])
    todo = [p for p in parts if not (shard_root / p.name).is_dir()]
    extra = len(finish) + 1
    counter = {"done": len(parts) - len(todo), "total": len(parts) + grid.nx * grid.ny + extra}
    progress(counter["done"], counter["total"])

    def tick(_: Any) -> None:
        counter["done"] += 1
        progress(counter["done"], counter["total"])

    # Shard: one streaming pass per tile (per part of a large tile).
    t = time.perf_counter()
    shard_args = [
        (
            plan["tiles"][p.tile]["path"],
            p.tile,
            grid,
            str(shard_root / p.name),
            1_000_000,
            params.get("scan_dimension"),
            p.start,
            p.stop,
        )
        for p in todo
    ]
    _run_tasks(executor, job_dir, shard_tile, shard_args, tick)
    shard_seconds = time.perf_counter() - t

    # Blocks: every block that received a point from any tile.
    sizes: dict[str, int] = {}
    for shard in (p for d in shard_root.iterdir() if d.is_dir() for p in d.glob("*.bin")):
        sizes[shard.stem] = sizes.get(shard.stem, 0) + shard.stat().st_size
    # Largest blocks first, so the last tasks to finish are short ones and
    # workers do not idle at the end of the job.
    names = sorted(sizes, key=lambda n: (-sizes[n], n))
    counter["total"] = len(parts) + len(names) + extra
    t = time.perf_counter()
    block_stats = _run_tasks(executor, job_dir, run_block, [(str(job_dir), n) for n in names], tick)
    block_seconds = time.perf_counter() - t

    t = time.perf_counter()
    (job_dir / "outputs").mkdir(exist_ok=True)
    _run_mixed_tasks(executor, job_dir, finish, tick, in_flight=executor.workers)
    finish_seconds = time.perf_counter() - t
    check_cancel(job_dir)
    _require_ground(output_path(job_dir, "dtm.tif"))
    timings = {
        "shard": shard_seconds,
        "blocks": block_seconds,
        "finish": finish_seconds,
        "total": time.perf_counter() - started,
    }
    names_out = outputs.write_report_and_item(job_dir, plan, params, block_stats, timings)
    tick(None)
    return names_out


def _require_ground(dtm: Path) -> None:
    """A successful job never has an empty DTM: fail it saying why instead."""
    if not dtm.exists():
        return
    import rasterio

    with rasterio.open(dtm) as ds:
        for _, window in ds.block_windows(1):
            if np.ma.count(ds.read(1, window=window, masked=True)):
                return
    raise ProcessingError(
        "no ground found: every cell of the DTM is empty (no point was classified as ground); "
        "the point data may be corrupt, or the parameters unsuited to it"
    )


def _plan(job_dir: Path, job: Mapping[str, Any]) -> dict[str, Any]:
    path = job_dir / "plan.json"
    if path.exists():
        return load_json(path)
    params = job["params"]
    infos = [read_tile_info(p) for p in job["inputs"]]
    crs_wkt, warnings = resolve_crs(infos, params.get("crs"))
    mins = (min(i.mins[0] for i in infos), min(i.mins[1] for i in infos))
    maxs = (max(i.maxs[0] for i in infos), max(i.maxs[1] for i in infos))
    area = sum(max(i.area, 1.0) for i in infos)
    density = sum(i.point_count for i in infos) / area
    buffer, warning = resolve_buffer(params, density)
    if warning:
        warnings.append(warning)
    grid = BlockGrid.over(
        mins, maxs, params["resolution"], params["block_size"], buffer, grid_alignment(params)
    )
    plan = {
        "tiles": [dict(i.__dict__) for i in infos],
        "density": density,
        "crs_wkt": crs_wkt,
        "crs": _crs_label(crs_wkt),
        "grid": grid.to_dict(),
        "warnings": warnings,
    }
    write_json_atomic(path, plan)
    return plan


@dataclass(frozen=True)
class Task:
    """A call to submit, once the tasks at positions ``after`` (same list) are done."""

    fn: Callable[..., Any]
    args: tuple
    after: tuple[int, ...] = ()


def _run_tasks(
    executor: Executor,
    job_dir: Path,
    fn: Callable[..., Any],
    arg_list: list[tuple],
    on_done: Callable[[Any], None],
) -> list[Any]:
    return _run_mixed_tasks(executor, job_dir, [Task(fn, a) for a in arg_list], on_done)


def _run_mixed_tasks(
    executor: Executor,
    job_dir: Path,
    tasks: list[Task],
    on_done: Callable[[Any], None],
    *,
    in_flight: int | None = None,
) -> list[Any]:
    """Submit every task as soon as the tasks it comes after are done; wait for
    all and return their results in list order.

    With ``in_flight``, at most that many tasks are submitted at a time and a
    free slot goes to the first ready task in list order: the list is a
    priority order (a pool runs what it was given first-come, first-served).
    The first failure cancels the rest and is raised; so is a dismissal seen
    between waits (running tasks see the marker themselves).
    """
    results: dict[int, Any] = {}
    futures: dict[int, Future] = {}
    position: dict[int, int] = {}  # id(future) -> task position
    waiting = set(range(len(tasks)))
    limit = in_flight or len(tasks)

    def submit_ready() -> None:
        for i in sorted(waiting):
            if len(futures) - len(results) >= limit:
                return
            if all(j in results for j in tasks[i].after):
                futures[i] = executor.submit(tasks[i].fn, *tasks[i].args)
                position[id(futures[i])] = i
                waiting.discard(i)

    try:
        submit_ready()
        while len(results) < len(tasks):
            running = [f for i, f in futures.items() if i not in results]
            if not running:
                raise RuntimeError(f"tasks {sorted(waiting)} wait on tasks that never run")
            done = executor.wait_any(running, timeout=0.5)
            for f in done:
                i = position[id(f)]
                results[i] = f.result()
                on_done(results[i])
            submit_ready()
            check_cancel(job_dir)
    except BaseException:
        for i, f in futures.items():
            if i not in results:
                f.cancel()
        raise
    return [results[i] for i in range(len(tasks))]


def clear_outputs(job_dir: Path) -> None:
    """Remove a job's intermediate and output files (after dismissal)."""
    for sub in ("shards", "blocks", "outputs"):
        shutil.rmtree(Path(job_dir) / sub, ignore_errors=True)


def job_path_profile(
    job_dir: Path,
    geometry: Mapping[str, Any],
    *,
    crs: str | None = None,
    spacing: float | None = None,
) -> Any:
    """Pitch and roll along a GeoJSON LineString over a finished job's DTM (see ``dtm_path_profile``)."""
    from terrasift.params import stage_params

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
    smooth: str = "gradient",
) -> Any:
    """Pitch and roll along a GeoJSON LineString over a DTM GeoTIFF.

    ``crs`` names the line's CRS: None for WGS 84 lon/lat (RFC 7946), ``"native"``
    for the DTM's CRS, or any CRS string. Raises ParameterError for a bad line.
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
    if crs == "native" or (crs is None and tile_crs is None):
        line = terrain.line_coordinates(dict(geometry), None)
    else:
        if tile_crs is None:
            raise ParameterError(
                "the DTM has no CRS: give the line in its coordinates (crs=native)"
            )
        line = terrain.line_coordinates(dict(geometry), tile_crs, crs or "EPSG:4326")
    length = float(np.sum(np.hypot(*np.diff(line, axis=0).T)))
    if length / spacing > 1_000_000:
        raise ParameterError(
            f"a {length:.0f} m path at {spacing} m spacing is over a million samples"
        )
    return terrain.path_profile(dtm, transform, line, spacing, median_size, smooth)
