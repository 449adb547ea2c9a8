"""The task a worker runs for one block: stages in order, core labels and rasters out.

``classify_block`` is pure (arrays in, arrays out); ``run_block`` is the task
wrapper that reads the block's shards and writes its result atomically, so a
crashed or repeated task never leaves a half result.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from terrasift.params import stage_params
from terrasift.tiling.blocks import BlockGrid, parse_block_name, read_block_points
from terrasift.workers import dem
from terrasift.workers.registry import get_stage

UNCLASSIFIED, GROUND, LOW_VEG, MED_VEG, HIGH_VEG, NOISE = 1, 2, 3, 4, 5, 7


@dataclass
class BlockResult:
    """Labels of the block's core points and the rasters of its core window."""

    tile: NDArray[np.uint16]
    index: NDArray[np.int64]
    classes: NDArray[np.uint8]
    window: tuple[int, int, int, int]  # row_off, col_off, rows, cols in the job raster
    rasters: dict[str, NDArray] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)


class _Timer:
    def __init__(self) -> None:
        self.times: dict[str, float] = {}

    def __call__(self, name: str) -> _Timer:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.times[self._name] = self.times.get(self._name, 0.0) + time.perf_counter() - self._t


def classify_block(
    points: NDArray,
    grid: BlockGrid,
    ix: int,
    iy: int,
    params: Mapping[str, Any],
    check_cancel: Callable[[], None] = lambda: None,
) -> BlockResult:
    """Run the stages on one block's core + halo points (a SHARD_DTYPE array).

    Every stage sees the halo so its decisions at the core edge match the
    neighbour's; only core points are labelled and only core cells rastered.
    """
    timer = _Timer()
    xyz = np.column_stack([points["x"], points["y"], points["z"]])
    core = points["core"].astype(bool)
    n = xyz.shape[0]
    labels = np.full(n, UNCLASSIFIED, np.uint8)
    stats: dict[str, Any] = {"points_core": int(core.sum()), "points_total": n}

    active = np.ones(n, dtype=bool)  # points still in the pipeline (not removed as noise)
    origin = params.get("sensor_origin")

    check_cancel()
    method = params["ground"]
    stage = get_stage(f"ground.{method}")
    gparams = stage_params(params, stage.id, params.get("ground.preset", "default"))
    with timer("ground"):
        is_ground = np.zeros(n, dtype=bool)
        if active.sum() >= 3:
            sub = xyz[active]
            kwargs = {"sensor_origin": np.asarray(origin, float)} if origin else {}
            is_ground[np.flatnonzero(active)] = stage.run(sub, gparams, **kwargs)
    labels[is_ground] = GROUND

    check_cancel()
    row_off, col_off, rows, cols = grid.core_window(ix, iy)
    xmin, _, _, ymax = grid.core_bounds(ix, iy)
    window = dem.Window(xmin, ymax, grid.resolution, rows, cols)
    with timer("dtm"):
        keep = active & (labels != NOISE)
        reach = dem.default_reach(int(keep.sum()), _block_area(grid), grid.resolution)
        valid = dem.data_reach_mask(xyz[keep], window, reach)
        dtm = dem.dtm_window(xyz[is_ground], window)
        dtm[~valid] = np.nan
        dsm = dem.dsm_window(xyz[keep], window)
        dsm[~valid] = np.nan
        dsm = np.fmax(dsm, dtm)

    counts = np.bincount(labels[core], minlength=32)
    stats["counts"] = {str(c): int(v) for c, v in enumerate(counts) if v}
    stats["timings"] = timer.times
    return BlockResult(
        tile=points["tile"][core],
        index=points["index"][core],
        classes=labels[core],
        window=(row_off, col_off, rows, cols),
        rasters={"dtm": dtm, "dsm": dsm},
        stats=stats,
    )


def _block_area(grid: BlockGrid) -> float:
    side = grid.block_size + 2 * grid.buffer
    return side * side


# ---------------------------------------------------------------- task wrapper


def block_result_path(job_dir: Path, name: str) -> Path:
    return Path(job_dir) / "blocks" / f"{name}.npz"


def run_block(job_dir: str, name: str) -> dict[str, Any]:
    """Task: classify block ``name`` of the job in ``job_dir``; returns its stats.

    Skips the work when the block's result already exists (resumed jobs).
    """
    from terrasift.pipeline import check_cancel, load_json  # local: pipeline imports this module

    job_dir_p = Path(job_dir)
    out = block_result_path(job_dir_p, name)
    stats_path = out.with_suffix(".json")
    if out.exists() and stats_path.exists():
        return json.loads(stats_path.read_text())
    check_cancel(job_dir_p)
    plan = load_json(job_dir_p / "plan.json")
    params = load_json(job_dir_p / "job.json")["params"]
    grid = BlockGrid(**plan["grid"])
    shard_dirs = [job_dir_p / "shards" / str(i) for i in range(len(plan["tiles"]))]
    points = read_block_points(shard_dirs, name)
    ix, iy = parse_block_name(name)
    t0 = time.perf_counter()
    result = classify_block(points, grid, ix, iy, params, lambda: check_cancel(job_dir_p))
    result.stats["seconds"] = time.perf_counter() - t0
    result.stats["name"] = name
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.npz")
    np.savez(
        tmp,
        tile=result.tile,
        index=result.index,
        classes=result.classes,
        window=np.asarray(result.window),
        **{f"raster_{k}": v for k, v in result.rasters.items()},
    )
    os.replace(tmp, out)
    tmp_stats = stats_path.with_suffix(".json.tmp")
    tmp_stats.write_text(json.dumps(result.stats))
    os.replace(tmp_stats, stats_path)
    return result.stats
