"""A job from inputs to outputs: plan, shard, blocks, finish — resumable at every step.

The job directory holds everything: ``job.json`` (inputs, parameters),
``plan.json`` (tiles, CRS, block grid; after sharding the ground density and,
for a ground-based scan, each scan position's geometry),
``shards/<tile part>/<block>.bin`` and ``occupancy.npy``,
``blocks/<block>.npz`` and ``outputs/``. Each task writes its result
atomically and is skipped when the result exists, so a restarted service or
a repeated ``process`` call redoes only what is missing. The CLI and the
service both drive jobs through ``run_job``.
"""

from __future__ import annotations

import heapq
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from terrasift.errors import ProcessingError
from terrasift.files import load_json, write_json
from terrasift.jobs import finish, report
from terrasift.jobs import survey as surveys
from terrasift.jobs.block import run_block
from terrasift.jobs.dirs import check_cancel, output_path
from terrasift.jobs.params import block_models
from terrasift.jobs.plan import plan_job
from terrasift.jobs.quicklooks import write_quicklooks
from terrasift.jobs.scan import measure_job_geometry
from terrasift.progress import JobProgress
from terrasift.tiling.blocks import (
    OCCUPANCY_FILE,
    BlockGrid,
    occupied_density,
    scan_reach,
    shard_parts,
    shard_tile,
)
from terrasift.workers.executors import Executor, Future

#: called with work done, total work and details (stage, message, warnings)
Progress = Callable[[int, int, Mapping[str, Any]], None]


def run_job(
    job_dir: Path, executor: Executor, progress: Progress | None = None, *, products: str = "all"
) -> list[str]:
    """Run (or resume) the job in ``job_dir`` on ``executor``; return output names.

    ``products="classified"`` writes only the classified point clouds (and the report).
    """
    job_dir = Path(job_dir).absolute()  # tasks may run on other machines' processes
    progress = progress or (lambda done, total, info: None)
    started = time.perf_counter()
    check_cancel(job_dir)
    preflight = getattr(executor, "preflight", None)  # Dask: workers see the job dir
    if preflight is not None:
        preflight(job_dir)
    job = load_json(job_dir / "job.json")
    params = job["params"]
    plan = plan_job(job_dir, job)
    grid = BlockGrid(**plan["grid"])
    n_tiles = len(plan["tiles"])

    # Finishing tasks: one classified point cloud per tile, and (all products)
    # the rasters, then slope/categories/features from the mosaicked DTM. The
    # list is in order of priority: the DTM first, since the terrain tasks
    # wait on it, then the long tasks, so the workers finish together. A job
    # that selected outputs runs only the tasks they need; the quicklooks come
    # last, from whatever the tasks before them wrote.
    want = finishing_wanted(job.get("outputs"), products)
    finishing: list[Task] = []
    survey = job.get("survey")
    if survey:  # a survey run: per-tile outputs of its output tiles, then the product
        # (derived products, each tile and feature square a task, then the publish:
        # ``_finish_survey``, once ``stage_derived`` said which are needed)
        n_out = len(survey["outputs"])
        finishing = [Task(surveys.write_tile_rasters, (str(job_dir), n)) for n in survey["outputs"]]
        finishing.append(Task(surveys.stage_derived, (str(job_dir),), after=tuple(range(n_out))))
        finishing += [
            Task(surveys.write_tile_classified, (str(job_dir), n)) for n in survey["outputs"]
        ]
        want = set()
    if "classified" in want:
        finishing = [Task(finish.write_classified, (str(job_dir), i)) for i in range(n_tiles)]
    if want - {"classified"}:
        dtm = Task(finish.write_raster, (str(job_dir), "dtm"))
        terrain = [
            Task(fn, (str(job_dir),), after=(0,))
            for key, fn in (("categories", finish.write_categories), ("slope", finish.write_slope))
            if key in want
        ]
        others = [
            Task(finish.write_raster, (str(job_dir), n))
            for n in finish.RASTERS
            if n != "dtm" and n in want
        ]
        finishing = [dtm, *finishing, *terrain, *others]
    if "quicklooks" in want:
        finishing.append(
            Task(write_quicklooks, (str(job_dir),), after=tuple(range(len(finishing))))
        )

    # Progress is work done: every task's points times its kind's measured cost.
    shard_root = job_dir / "shards"
    parts = shard_parts([t["point_count"] for t in plan["tiles"]])
    todo = [p for p in parts if not (shard_root / p.name).is_dir()]
    points = sum(int(t["point_count"]) for t in plan["tiles"])
    meter = JobProgress(progress, points, executor.workers, plan.get("warnings"))
    for p in parts:
        meter.add("shard", p.name, "shard", p.stop - p.start, done=p not in todo)
    for i, task in enumerate(finishing):
        kind = task.fn.__name__.removeprefix("write_")
        if survey:
            kind, weight = _SURVEY_COST[kind]
            tile_points = survey["tiles"][task.args[1]]["points"] if len(task.args) > 1 else points
            meter.add("finish", i, kind, weight * tile_points)
            continue
        tile_points = plan["tiles"][task.args[1]]["point_count"] if kind == "classified" else 0
        meter.add("finish", i, kind, tile_points or points)
    if survey:  # the derived products and the publish, counted as categories over the survey
        meter.add(
            "finish", "derived", "categories", sum(t["points"] for t in survey["tiles"].values())
        )
    meter.add("report", "report", "report", points)
    meter.reserve("blocks", "block")
    meter.enter("shard")

    # Shard: one streaming pass per tile (per part of a large tile).
    t = time.perf_counter()
    reach = None
    if todo and params.get("sensor_origin"):
        # each scan position's farthest return over every part: the copies along its
        # rays stop there (else they ran to the grid's edge: on a 1.2 km grid 7.8x the
        # records of plain sharding for a scan 160 m across)
        found = _run_tasks(
            executor,
            job_dir,
            scan_reach,
            [
                (
                    plan["tiles"][p.tile]["path"],
                    params.get("sensor_origin"),
                    params.get("scan_dimension"),
                    p.start,
                    p.stop,
                    plan.get("input_roots"),
                )
                for p in parts
            ],
            lambda i, _: None,
            meter.report,
        )
        reach = [max(v) for v in zip(*found, strict=True)]
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
            plan.get("input_roots"),
            float(plan.get("occupancy_cell", 0.0)),
            bool(params.get("sensor_origin")),  # ground-based: GPS time gives scan order
            params.get("sensor_origin"),  # ground-based: the blocks behind each return
            reach,  # ... up to each position's farthest return
        )
        for p in todo
    ]
    _run_tasks(
        executor,
        job_dir,
        shard_tile,
        shard_args,
        lambda i, _: meter.done("shard", todo[i].name),
        meter.report,
    )
    shard_seconds = time.perf_counter() - t
    _add_ground_density(job_dir, plan, [shard_root / p.name for p in parts])
    _add_scan_geometry(job_dir, plan, [shard_root / p.name for p in parts], params)

    # Blocks: every block that received a point from any tile.
    sizes: dict[str, int] = {}
    for shard in (
        p
        for d in (shard_root.iterdir() if shard_root.is_dir() else ())
        if d.is_dir() and not d.name.startswith(".")
        for p in d.glob("*.bin")
    ):
        sizes[shard.stem] = sizes.get(shard.stem, 0) + shard.stat().st_size
    # Largest blocks first, so the last tasks to finish are short ones and
    # workers do not idle at the end of the job.
    if survey:  # only the blocks of the output tiles; the others' points are halo only
        wanted = set(survey["blocks"])
        sizes = {n: v for n, v in sizes.items() if n in wanted}
    names = sorted(sizes, key=lambda n: (-sizes[n], n))
    meter.split("blocks", sizes, "block")
    meter.enter("blocks")
    t = time.perf_counter()
    block_stats = _run_tasks(
        executor,
        job_dir,
        run_block,
        [(str(job_dir), n) for n in names],
        lambda i, _: meter.done("blocks", names[i]),
        meter.report,
    )
    block_seconds = time.perf_counter() - t

    t = time.perf_counter()
    (job_dir / "outputs").mkdir(exist_ok=True)
    meter.enter("finish")
    finished = _run_mixed_tasks(
        executor,
        job_dir,
        finishing,
        lambda i, _: meter.done("finish", i),
        in_flight=executor.workers,
        heartbeat=meter.report,
    )
    if survey:
        _finish_survey(executor, job_dir, finished[len(survey["outputs"])], meter.report)
        meter.done("finish", "derived")
    finish_seconds = time.perf_counter() - t
    check_cancel(job_dir)
    if survey:  # published into the survey's product; the run keeps its summary only
        if not survey.get("keep_intermediates"):  # the retention setting keeps them
            for sub in ("shards", "blocks", "work", "outputs/tiles"):
                shutil.rmtree(job_dir / sub, ignore_errors=True)
        meter.done("report", "report")
        return ["survey.json"]
    _require_ground(output_path(job_dir, "dtm.tif"))
    timings = {
        "shard": shard_seconds,
        "blocks": block_seconds,
        "finish": finish_seconds,
        "total": time.perf_counter() - started,
    }
    meter.enter("report")
    names_out = report.write_report_and_item(job_dir, plan, params, block_stats, timings)
    meter.done("report", "report")
    if job.get("outputs") is not None:
        keep = set(job["outputs"])
        names_out = [
            n
            for n in names_out
            if n in keep or (n.startswith("classified") and "classified.laz" in keep)
        ]
    return names_out


def _finish_survey(
    executor: Executor, job_dir: Path, stage: Mapping[str, Any], heartbeat: Callable[[], None]
) -> None:
    """A survey run's derived products as parallel tasks (the feature squares, longest,
    first; then each tile's slope and categories), then the publish after them all."""
    jd = str(job_dir)
    tasks = [Task(surveys.search_feature_square, (jd, k)) for k in stage["search"]]
    tasks += [Task(surveys.write_tile_derived, (jd, n)) for n in stage["tiles"]]
    tasks.append(Task(surveys.publish, (jd,), after=tuple(range(len(tasks)))))
    _run_mixed_tasks(
        executor, job_dir, tasks, lambda i, _: None, in_flight=executor.workers, heartbeat=heartbeat
    )


#: progress kind and weight (per tile point) of a survey run's finishing tasks
_SURVEY_COST = {
    "tile_rasters": ("raster", 4.0),
    "tile_classified": ("classified", 1.0),
    "stage_derived": ("categories", 0.0),
}

#: finishing work each selectable output needs (outputs not named need none beyond the report)
OUTPUT_TASKS = {
    "classified.laz": {"classified"},
    "dtm.tif": {"dtm"},
    "dsm.tif": {"dsm"},
    "chm.tif": {"chm"},
    "coverage.tif": {"coverage"},
    "slope.tif": {"slope"},
    "categories.tif": {"categories"},
    "features.geojson": {"categories"},
    "features.native.geojson": {"categories"},
    "thumbnail.png": {"quicklooks", "dtm"},
    "hillshade.png": {"quicklooks", "dtm"},
    "chm.png": {"quicklooks", "chm"},
    "coverage.png": {"quicklooks", "coverage"},
    "categories.png": {"quicklooks", "categories"},
    "features.png": {"quicklooks", "dtm", "categories"},
    "steep_blocks.png": {"quicklooks", "dtm"},
}


def finishing_wanted(selected: list[str] | None, products: str = "all") -> set[str]:
    """Finishing tasks for the selected outputs (None: every output of ``products``)."""
    if products == "classified":
        return {"classified"}
    if selected is None:
        return set().union(*OUTPUT_TASKS.values())
    return set().union(set(), *(OUTPUT_TASKS.get(n, set()) for n in selected))


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
    on_done: Callable[[int, Any], None],
    heartbeat: Callable[[], None] | None = None,
) -> list[Any]:
    return _run_mixed_tasks(
        executor, job_dir, [Task(fn, a) for a in arg_list], on_done, heartbeat=heartbeat
    )


def _run_mixed_tasks(
    executor: Executor,
    job_dir: Path,
    tasks: list[Task],
    on_done: Callable[[int, Any], None],
    *,
    in_flight: int | None = None,
    heartbeat: Callable[[], None] | None = None,
) -> list[Any]:
    """Submit every task as soon as the tasks it comes after are done; wait for
    all and return their results in list order.

    At most ``in_flight`` tasks (default: four per worker, at least 16) are
    submitted at a time, and a free slot goes to the first ready task in list
    order: the list is a priority order (a pool runs what it was given
    first-come, first-served). Each wait looks at the submitted tasks only, so
    the driver's work grows linearly with the number of tasks.
    ``on_done(position, result)`` follows each task; ``heartbeat`` each wait.
    The first failure cancels the rest and is raised; so is a dismissal seen
    between waits (running tasks see the marker themselves).
    """
    results: dict[int, Any] = {}
    running: dict[Future, int] = {}
    dependents: dict[int, list[int]] = {}
    blocked = [len(t.after) for t in tasks]
    for i, t in enumerate(tasks):
        for j in t.after:
            dependents.setdefault(j, []).append(i)
    ready = [i for i, n in enumerate(blocked) if n == 0]
    heapq.heapify(ready)

    def submit_ready() -> None:
        limit = in_flight or max(4 * executor.workers, 16)
        while ready and len(running) < limit:
            i = heapq.heappop(ready)
            running[executor.submit(tasks[i].fn, *tasks[i].args)] = i

    try:
        submit_ready()
        while len(results) < len(tasks):
            if not running:
                waiting = sorted(set(range(len(tasks))) - set(results))
                raise RuntimeError(f"tasks {waiting} wait on tasks that never run")
            for f in executor.wait_any(list(running), timeout=0.5):
                i = running.pop(f)
                results[i] = f.result()
                on_done(i, results[i])
                for k in dependents.get(i, ()):
                    blocked[k] -= 1
                    if blocked[k] == 0:
                        heapq.heappush(ready, k)
            if heartbeat is not None:
                heartbeat()
            submit_ready()
            check_cancel(job_dir)
    except BaseException:
        for f in running:
            f.cancel()
        raise
    return [results[i] for i in range(len(tasks))]


def _add_ground_density(job_dir: Path, plan: dict[str, Any], shard_dirs: list[Path]) -> None:
    """Record in ``plan.json`` the job's points per m² of occupied area, from the
    cells every shard part recorded: the one density the ground stage of every
    block follows (``jobs.params.with_ground_density``), so blocks cut from one
    tile bin and mask alike. Left out when a part has no record (shards of an
    older job resumed) or the plan has no cell size (survey runs)."""
    cell = float(plan.get("occupancy_cell", 0.0))
    if "ground_density" in plan or cell <= 0:
        return
    files = [d / OCCUPANCY_FILE for d in shard_dirs]
    if not files or not all(f.exists() for f in files):
        return
    import numpy as np

    points = sum(int(t["point_count"]) for t in plan["tiles"])
    plan["ground_density"] = occupied_density(points, [np.load(f) for f in files], cell)
    write_json(job_dir / "plan.json", plan, indent=2)


def _add_scan_geometry(
    job_dir: Path, plan: dict[str, Any], shard_dirs: list[Path], params: Mapping[str, Any]
) -> None:
    """Record in ``plan.json`` the geometry of each scan position of a ground-based job,
    measured once from the points of all blocks (``jobs.scan``): every block's mixed
    stage then follows one step, noise and footprint per position, however few of its
    points a block holds. Left out for airborne jobs and when already recorded."""
    if "scan_geometry" in plan:
        return
    models = block_models(params)
    if not models.sensor_origin:
        return
    plan["scan_geometry"] = measure_job_geometry(shard_dirs, models.sensor_origin, models.mixed)
    write_json(job_dir / "plan.json", plan, indent=2)


def _require_ground(dtm: Path) -> None:
    """A successful job never has an empty DTM: fail it saying why instead."""
    if not dtm.exists():
        return
    import numpy as np
    import rasterio

    with rasterio.open(dtm) as ds:
        for _, window in ds.block_windows(1):
            if np.ma.count(ds.read(1, window=window, masked=True)):
                return
    raise ProcessingError(
        "no ground found: every cell of the DTM is empty (no point was classified as ground); "
        "the point data may be corrupt, or the parameters unsuited to it"
    )
