"""One block through the stages: core labels and rasters out, pure arrays in and out.

``classify_block`` runs the registered block steps (``registry.block_steps``)
in their order on one block's core + halo points, with parameter models the
jobs room has built (``BlockModels``). It reads and writes no files; the task
wrapper that does is ``terrasift.jobs.block``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from terrasift.tiling.blocks import BlockGrid
from terrasift.workers.ground.landforms import LandformParams
from terrasift.workers.ground.lowpoints import LowPointParams
from terrasift.workers.ground.lowveg import LowVegParams
from terrasift.workers.ground.rotation import RotationParams, SteepParams
from terrasift.workers.mixed import MixedParams
from terrasift.workers.objects import ObjectParams
from terrasift.workers.registry import Stage, StageParams, block_steps
from terrasift.workers.scan_geometry import ScanGeometry
from terrasift.workers.terrain import TerrainParams
from terrasift.workers.vegetation import VegetationParams

UNCLASSIFIED, GROUND, LOW_VEG, MED_VEG, HIGH_VEG, BUILDING, NOISE = 1, 2, 3, 4, 5, 6, 7


@dataclass(frozen=True)
class BlockModels:
    """The validated parameter models of a job's block stages, built once per job."""

    ground: Stage
    """The ground method (a ``ground.*`` registry entry)."""
    ground_params: StageParams
    """Its parameters, with the job's preset."""
    rotation_ground_params: StageParams
    """Its parameters for the rotated runs (the rotation's preset)."""
    lowpoints: LowPointParams
    steep: SteepParams
    rotation: RotationParams
    rotation_mode: Literal["auto", "off", "always"]
    vegetation: VegetationParams
    terrain: TerrainParams
    mixed: MixedParams
    objects: ObjectParams = field(default_factory=ObjectParams)
    """Buildings, noise and the input classes kept."""
    sensor_origin: tuple[tuple[float, float, float], ...] | None = None
    """Scan positions of a ground-based scan; None for airborne data."""
    scan_geometry: tuple[ScanGeometry | None, ...] | None = None
    """Per scan position, its geometry measured once for the whole job (None: each
    block measures its own)."""
    landforms: LandformParams | None = None
    """The steep-landform rule after the ground stage (None: not run)."""
    lowveg: LowVegParams | None = None
    """The low-vegetation rule after the ground stage (None: not run)."""


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


@dataclass
class Block:
    """One block's points in canonical order, and what the steps have found so far.

    ``act`` indexes the points still in the pipeline (mixed measurements
    leave it) and ``sub`` holds their coordinates; ``ground`` and ``low``
    are flags over ``sub``.
    """

    xyz: NDArray[np.float64]
    scan_id: NDArray
    core: NDArray[np.bool_]
    grid: BlockGrid
    ix: int
    iy: int
    density: float
    """The job's mean points per m²: one value for every block, so blocks judge alike."""
    check_cancel: Callable[[], None]
    return_number: NDArray | None = None
    number_of_returns: NDArray | None = None
    given: NDArray | None = None
    """The input's classes (kept classes)."""
    gps_time: NDArray | None = None
    """Each point's GPS time (ground-based jobs; NaN where the file has none)."""
    shadow: NDArray[np.bool_] | None = None
    """Points from in front of the block along the sensor's rays (not core, not halo):
    neighbouring beams for the mixed step, left out of every other step."""
    labels: NDArray[np.uint8] = field(init=False)
    act: NDArray[np.intp] = field(init=False)
    sub: NDArray[np.float64] = field(init=False)
    ground: NDArray[np.bool_] = field(init=False)
    low: NDArray[np.bool_] = field(init=False)
    building: NDArray[np.bool_] | None = None
    """Flags over ``sub`` (objects step); ``noise`` likewise, ``height`` above ground."""
    noise: NDArray[np.bool_] | None = None
    height: NDArray[np.float64] | None = None
    surface: Any = None
    rasters: dict[str, NDArray] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    timer: _Timer = field(default_factory=_Timer)

    def __post_init__(self) -> None:
        n = self.xyz.shape[0]
        self.labels = np.full(n, UNCLASSIFIED, np.uint8)
        self.act = np.arange(n)
        self.sub = self.xyz
        self.ground = np.zeros(n, dtype=bool)
        self.low = np.zeros(n, dtype=bool)


def classify_block(
    points: NDArray,
    grid: BlockGrid,
    ix: int,
    iy: int,
    models: BlockModels,
    density: float,
    check_cancel: Callable[[], None] = lambda: None,
) -> BlockResult:
    """Run the block steps on one block's core + halo points (a SHARD_DTYPE array).

    Order: mixed measurements (scans with a sensor origin) → ground (with the
    steepness test, rotated ×8 and OR'ed on steep blocks) → ground surface →
    vegetation bins → roughness → DTM, DSM, coverage. Every stage sees the
    halo so its decisions at the core edge match the neighbour's; only core
    points are labelled and only core cells rastered. ``density`` is the
    job's mean points per m².
    """
    # A canonical order, so labels do not depend on how the points were split
    # into files or shards (stages break ties by position in the array).
    # Fields are gathered one by one: a gather of the packed records is ~5x slower.
    order = canonical_order(points["x"], points["y"], points["z"])
    xyz = np.column_stack([points["x"][order], points["y"][order], points["z"][order]])
    core = points["core"][order] == 1
    names = points.dtype.names or ()
    block = Block(
        xyz,
        points["scan_id"][order],
        core,
        grid,
        ix,
        iy,
        density,
        check_cancel,
        points["return_number"][order] if "return_number" in names else None,
        points["number_of_returns"][order] if "number_of_returns" in names else None,
        points["classification"][order] if "classification" in names else None,
        points["gps_time"][order] if "gps_time" in names else None,
    )
    shadow = points["core"][order] == 2
    if shadow.any():
        # returns in front of the block, for the mixed step only (``assign_shadow``)
        block.shadow = shadow
        block.act = np.flatnonzero(~shadow)
        block.sub = block.xyz[block.act]
    block.stats.update({"points_core": int(core.sum()), "points_total": xyz.shape[0]})
    for step in block_steps():
        step.run(block, models)

    labels = block.labels
    counts = np.bincount(labels[core], minlength=32)
    block.stats["counts"] = {str(c): int(v) for c, v in enumerate(counts) if v}
    block.stats["timings"] = block.timer.times
    return BlockResult(
        tile=points["tile"][order[core]],
        index=points["index"][order[core]],
        classes=labels[core],
        window=grid.core_window(ix, iy),
        rasters=block.rasters,
        stats=block.stats,
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
