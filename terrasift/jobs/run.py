"""A job from inputs to outputs: plan, shard, blocks, finish — resumable at every step.

The job directory holds everything: ``job.json`` (inputs, parameters),
``plan.json`` (tiles, CRS, block grid), ``shards/<tile>/<block>.bin``,
``blocks/<block>.npz`` and ``outputs/``. Each task writes its result
atomically and is skipped when the result exists, so a restarted service or
a repeated ``process`` call redoes only what is missing. The CLI and the
service both drive jobs through ``run_job``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from terrasift.errors import ProcessingError
from terrasift.files import load_json
from terrasift.jobs import finish, report
from terrasift.jobs.block import run_block
from terrasift.jobs.dirs import check_cancel, output_path
from terrasift.jobs.plan import plan_job
from terrasift.tiling.blocks import BlockGrid, shard_parts, shard_tile
from terrasift.workers.executors import Executor, Future

Progress = Callable[[int, int], None]


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
    plan = plan_job(job_dir, job)
    grid = BlockGrid(**plan["grid"])
    n_tiles = len(plan["tiles"])

    # Finishing tasks: one classified point cloud per tile, and (all products)
    # the rasters, then slope/categories/features from the mosaicked DTM. The
    # list is in order of priority: the DTM first, since the terrain tasks
    # wait on it, then the long tasks, so the workers finish together.
    finishing: list[Task] = [
        Task(finish.write_classified, (str(job_dir), i)) for i in range(n_tiles)
    ]
    if products == "all":
        dtm = Task(finish.write_raster, (str(job_dir), "dtm"))
        terrain = [
            Task(fn, (str(job_dir),), after=(0,))
            for fn in (finish.write_categories, finish.write_slope)
        ]
        others = [
            Task(finish.write_raster, (str(job_dir), n)) for n in finish.RASTERS if n != "dtm"
        ]
        finishing = [dtm, *finishing, *terrain, *others]

    # Progress counts tasks: shards, blocks, finishing tasks, the report.
    shard_root = job_dir / "shards"
    parts = shard_parts([t["point_count"] for t in plan["tiles"]])
    todo = [p for p in parts if not (shard_root / p.name).is_dir()]
    extra = len(finishing) + 1
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
    for shard in (
        p
        for d in shard_root.iterdir()
        if d.is_dir() and not d.name.startswith(".")
        for p in d.glob("*.bin")
    ):
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
    _run_mixed_tasks(executor, job_dir, finishing, tick, in_flight=executor.workers)
    finish_seconds = time.perf_counter() - t
    check_cancel(job_dir)
    _require_ground(output_path(job_dir, "dtm.tif"))
    timings = {
        "shard": shard_seconds,
        "blocks": block_seconds,
        "finish": finish_seconds,
        "total": time.perf_counter() - started,
    }
    names_out = report.write_report_and_item(job_dir, plan, params, block_stats, timings)
    tick(None)
    return names_out


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
