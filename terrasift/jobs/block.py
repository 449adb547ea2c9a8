"""The block task: read a block's shards, run ``classify_block``, write its result.

The job's stage models are built from its parameters (``params.block_models``)
once per task, so the science in ``terrasift.workers`` never sees a job.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from terrasift.files import atomic_path, load_json, write_json
from terrasift.jobs.dirs import block_result_path, check_cancel
from terrasift.jobs.params import (
    block_models,
    job_anchor,
    with_ground_anchor,
    with_ground_density,
)
from terrasift.jobs.scan import job_geometry
from terrasift.tiling.blocks import BlockGrid, parse_block_name, read_block_points, shard_parts
from terrasift.workers.block import classify_block


def run_block(job_dir: str, name: str) -> dict[str, Any]:
    """Task: classify block ``name`` of the job in ``job_dir``; returns its stats.

    Skips the work when the block's result already exists (resumed jobs).
    """
    job_dir_p = Path(job_dir)
    out = block_result_path(job_dir_p, name)
    stats_path = out.with_suffix(".json")
    if out.exists() and stats_path.exists():
        return load_json(stats_path)
    check_cancel(job_dir_p)
    plan = load_json(job_dir_p / "plan.json")
    job = load_json(job_dir_p / "job.json")
    models = with_ground_anchor(
        with_ground_density(block_models(job["params"]), plan.get("ground_density")),
        job_anchor(job, plan),
    )
    if plan.get("scan_geometry"):
        models = dataclasses.replace(models, scan_geometry=job_geometry(plan["scan_geometry"]))
    grid = BlockGrid(**plan["grid"])
    shard_dirs = [
        job_dir_p / "shards" / p.name
        for p in shard_parts([t["point_count"] for t in plan["tiles"]])
    ]
    points = read_block_points(shard_dirs, name)
    ix, iy = parse_block_name(name)
    t0 = time.perf_counter()
    result = classify_block(
        points,
        grid,
        ix,
        iy,
        models,
        float(plan.get("density", 1.0)),
        lambda: check_cancel(job_dir_p),
    )
    result.stats["seconds"] = time.perf_counter() - t0
    result.stats["name"] = name
    arrays: dict[str, Any] = {
        "tile": result.tile,
        "index": result.index,
        "classes": result.classes,
        "window": np.asarray(result.window),
        **{f"raster_{k}": v for k, v in result.rasters.items()},
    }
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    write_json(stats_path, result.stats)
    return result.stats
