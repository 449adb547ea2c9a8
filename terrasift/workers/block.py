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

from terrasift.errors import ProcessingError
from terrasift.params import stage_params
from terrasift.tiling.blocks import BlockGrid, parse_block_name, read_block_points, shard_parts
from terrasift.workers import dem
from terrasift.workers.bins import Grid
from terrasift.workers.ground import landforms, lowpoints, rotation
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

    Order: mixed measurements (scans with a sensor origin) → steepness test →
    ground (rotated ×8 and OR'ed on steep blocks) → vegetation bins → DTM,
    DSM, coverage → point classes. Every stage sees the halo so its decisions
    at the core edge match the neighbour's; only core points are labelled and
    only core cells rastered.
    """
    timer = _Timer()
    # A canonical order, so labels do not depend on how the points were split
    # into files or shards (stages break ties by position in the array).
    # Fields are gathered one by one: a gather of the packed records is ~5x slower.
    order = canonical_order(points["x"], points["y"], points["z"])
    xyz = np.column_stack([points["x"][order], points["y"][order], points["z"][order]])
    core = points["core"][order].astype(bool)
    n = xyz.shape[0]
    labels = np.full(n, UNCLASSIFIED, np.uint8)
    stats: dict[str, Any] = {"points_core": int(core.sum()), "points_total": n}
    origins = params.get("sensor_origin")

    # Mixed measurements leave the pipeline before anything else sees them.
    active = np.ones(n, dtype=bool)
    if origins:
        check_cancel()
        with timer("mixed"):
            mixed = _mark_mixed(xyz, points["scan_id"][order], origins, params)
        labels[mixed.marked] = NOISE
        active &= ~mixed.marked
        stats["mixed"] = {
            "marked": int(mixed.marked[core].sum()),
            "unclassified": int(mixed.unclassified[core].sum()),
            "loss_rate": float(mixed.unclassified[core].mean()) if core.any() else 0.0,
        }
    act = np.flatnonzero(active)
    sub = xyz[act]

    # Ground, rotated on steep blocks.
    check_cancel()
    last = points["return_number"][order][act] >= points["number_of_returns"][order][act]
    is_ground_sub, low_sub, stats["steep"] = _ground(sub, params, origins, timer, last)
    is_ground = np.zeros(n, dtype=bool)
    is_ground[act] = is_ground_sub
    labels[is_ground] = GROUND
    labels[act[low_sub]] = NOISE
    stats["low_points"] = int(np.count_nonzero(low_sub[core[act]]))

    # Vegetation bins on the core window, and vegetation classes for the points in them.
    check_cancel()
    xmin, ymin, xmax, ymax = grid.core_bounds(ix, iy)
    from terrasift.workers import vegetation

    vparams = stage_params(params, "vegetation")
    if vparams.support is None:
        # One support window for the whole job, from its mean density, so
        # neighbouring blocks judge bins alike.
        support = vegetation.support_for_density(
            float(params.get("_density", 1.0)), vparams.cell, vparams.min_points
        )
        vparams = vparams.model_copy(update={"support": support})
    c = vparams.cell
    vgrid = Grid(xmin, ymin, c, int(round((xmax - xmin) / c)), int(round((ymax - ymin) / c)))
    pad = 7  # bins: the widest support window reaches this far into the halo
    hgrid = Grid(xmin - pad * c, ymin - pad * c, c, vgrid.nx + 2 * pad, vgrid.ny + 2 * pad)
    # One ground TIN (1 m vertices, lowest ground only) for vegetation heights and the DTM.
    row_off, col_off, rows, cols = grid.core_window(ix, iy)
    window = dem.Window(xmin, ymax, grid.resolution, rows, cols)
    with timer("dtm"):
        surface = dem.ground_tin(sub[is_ground_sub], max(grid.resolution, 1.0))
    with timer("vegetation"):
        veg = vegetation.classify_bins(sub, is_ground_sub, hgrid, vparams, surface=surface).crop(
            vgrid
        )
        if surface is not None:
            flat = vgrid.index(sub[:, 0], sub[:, 1])
            in_veg = (flat >= 0) & (veg.bin_class[np.maximum(flat, 0)] >= vegetation.BUSH)
            pick = in_veg & ~is_ground_sub & ~low_sub
            hag = sub[pick, 2] - surface(sub[pick, 0], sub[pick, 1])
            labels[act[pick]] = vegetation.height_classes(hag)
    stats["vegetation"] = veg.counts
    stats["vegetation_nogo"] = int(veg.nogo.sum())

    # Roughness gauge over the core's bins (ground points, plane per accepted bin).
    from terrasift.workers import terrain

    tparams = stage_params(params, "terrain")
    # Sparse clouds get whole multiples of the cell, so a bin expects twice
    # min_points and the gauge does not go empty (same for every block).
    density = float(params.get("_density", 1.0))
    rcell = tparams.cell * max(
        1, int(np.ceil(np.sqrt(2 * tparams.min_points / max(density, 1e-6)) / tparams.cell))
    )
    rgrid = Grid(xmin, ymin, rcell, int((xmax - xmin) // rcell), int((ymax - ymin) // rcell))
    with timer("roughness"):
        rough = terrain.roughness(sub[is_ground_sub], rgrid, tparams)
    stats["roughness_sums"] = [rough.n_bins, rough.mean_sx, rough.mean_sy, rough.m2_sx, rough.m2_sy]
    stats["roughness_cell"] = rcell

    # Elevation models on the core window.
    check_cancel()
    with timer("dtm"):
        # From the job's density, like the supports above: a block's own count
        # over its nominal area makes a half-empty edge block reach further
        # into a lake than its neighbour, and their nodata edges disagree.
        reach = dem.default_reach(float(params.get("_density", 1.0)), grid.resolution)
        valid = dem.data_reach_mask(sub, window, reach)
        dtm = dem.sample_window(surface, window)
        dtm[~valid] = np.nan
        dsm = dem.dsm_window(sub, window)
        dsm[~valid] = np.nan
        dsm = np.fmax(dsm, dtm)

    counts = np.bincount(labels[core], minlength=32)
    stats["counts"] = {str(c): int(v) for c, v in enumerate(counts) if v}
    stats["timings"] = timer.times
    return BlockResult(
        tile=points["tile"][order[core]],
        index=points["index"][order[core]],
        classes=labels[core],
        window=(row_off, col_off, rows, cols),
        rasters={"dtm": dtm, "dsm": dsm, "coverage": veg.raster()},
        stats=stats,
    )


def canonical_order(x: NDArray, y: NDArray, z: NDArray) -> NDArray[np.int64]:
    """Indices sorting points by (x, y, z), equal points in input order: the
    order of ``np.lexsort((z, y, x))``.

    When every coordinate lies on a 1 mm lattice (LAS scales of a millimetre
    or coarser), the three are packed into one int64 key whose sort is ~10x
    faster than the three-key lexsort; otherwise the lexsort runs.
    """
    if x.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = [v - v.min() for v in (x, y, z)]
    q = [np.round(d * 1000.0).astype(np.int64) for d in offsets]
    on_lattice = all(np.abs(k * 0.001 - d).max() < 1e-5 for k, d in zip(q, offsets, strict=True))
    bits = [max(int(k.max()).bit_length(), 1) for k in q]
    if not on_lattice or sum(bits) > 63:
        return np.lexsort((z, y, x))
    key = (q[0] << (bits[1] + bits[2])) | (q[1] << bits[2]) | q[2]
    # An unstable sort is ~4x faster than a stable one; equal keys (duplicate
    # points, rare) are then put back in input order run by run.
    order = np.argsort(key)
    ks = key[order]
    tie = np.flatnonzero(ks[1:] == ks[:-1])
    if tie.size:
        pos = np.union1d(tie, tie + 1)
        run = np.cumsum(
            np.r_[True, ks[pos[1:]] != ks[pos[:-1]]] | np.r_[True, pos[1:] != pos[:-1] + 1]
        )
        order[pos] = order[pos][np.lexsort((order[pos], run))]
    return order


def _mark_mixed(xyz: NDArray, scan_id: NDArray, origins: list, params: Mapping[str, Any]) -> Any:
    from terrasift.workers import mixed

    origin_arr = np.asarray(origins, dtype=np.float64)
    ids = None
    if origin_arr.shape[0] > 1:
        ids = scan_id.astype(np.int64)
        if ids.max(initial=0) >= origin_arr.shape[0]:
            raise ProcessingError(
                f"scan id {int(ids.max())} has no sensor origin ({origin_arr.shape[0]} given)"
            )
    else:
        origin_arr = origin_arr[0]
    return mixed.mark_mixed(xyz, stage_params(params, "mixed"), origin_arr, ids)


def _ground(
    xyz: NDArray,
    params: Mapping[str, Any],
    origins: list | None,
    timer: _Timer,
    last_return: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], dict[str, Any]]:
    """Ground labels and isolated low points (taken out of the ground), with the
    steepness test and rotated classification of DESIGN §5.3."""
    stage = get_stage(f"ground.{params['ground']}")
    kwargs = {"sensor_origin": np.asarray(origins[0], float)} if origins else {}
    steep_info: dict[str, Any] = {}
    none = np.zeros(xyz.shape[0], dtype=bool)
    if xyz.shape[0] < 3:
        return none, none, steep_info
    gparams = stage_params(params, stage.id, params.get("ground.preset", "default"))
    lparams = stage_params(params, "ground.lowpoints")

    def without_low(is_ground: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        with timer("low_points"):
            low = lowpoints.isolated_low_points(xyz, is_ground, lparams)
        return is_ground & ~low, low

    with timer("ground"):
        is_ground = np.asarray(stage.run(xyz, gparams, **kwargs), dtype=bool)
        # Mesas, buttes and steep hills the filter removed as if buildings.
        is_ground = landforms.restore_landforms(
            xyz, is_ground, stage_params(params, "ground.landforms")
        )
    is_ground, low = without_low(is_ground)
    mode = params.get("rotation", "auto")
    if mode == "off":
        return is_ground, low, steep_info

    # The test runs on the block's ground points: on the raw cloud, building
    # walls would make most urban blocks "steep".
    with timer("steep_test"):
        test = rotation.steepness(xyz[is_ground], stage_params(params, "ground.steep"))
    steep_info = {
        "facet_share": float(test.facet_share),
        "steep": bool(test.steep),
        "facets": int(test.n_facets),
    }
    if not (test.steep or mode == "always"):
        return is_ground, low, steep_info
    rparams = stage_params(
        params, "ground.rotation", stage.id
    )  # per-method preset (RotationParams.presets)
    cparams = stage_params(params, stage.id, rparams.ground_preset)
    # Seeded rotated runs where the method can grow from the labels found so far (ptd).
    ground, seeded = rotation.bind_ground(stage, cparams, **kwargs)
    with timer("rotation"):
        result = rotation.classify_rotated(
            xyz,
            ground,
            rparams,
            unrotated=None if rparams.rerun_unrotated else is_ground,
            seeded=seeded,
            last_return=last_return,
        )
    steep_info["rotated"] = True
    steep_info["added_per_rotation"] = [int(a) for a in result.added]
    is_ground, low = without_low(np.asarray(result.is_ground, dtype=bool))
    return is_ground, low, steep_info


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
    params = {**load_json(job_dir_p / "job.json")["params"], "_density": plan.get("density", 1.0)}
    grid = BlockGrid(**plan["grid"])
    shard_dirs = [
        job_dir_p / "shards" / p.name
        for p in shard_parts([t["point_count"] for t in plan["tiles"]])
    ]
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
