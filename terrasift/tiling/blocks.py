"""The block grid over a job's area, and one streaming pass per tile into block shards.

Blocks are squares of ``block_size`` laid from a corner snapped to the raster
grid, so each block's core covers whole raster cells and mosaics have no
half-pixel seams. A point belongs to the core of exactly one block (half-open
intervals [x0, x0 + B)), and is copied into the halo of every neighbour whose
core lies within ``buffer`` of it, corners included.

While sharding, each pass also records the cells its points occupy
(``occupied_cells``), so a job can measure its density over the area its
points cover, voids left out, once for all of its blocks
(``occupied_density``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from terrasift.files import atomic_path
from terrasift.tiling.lasfile import iter_chunks

SHARD_DTYPE = np.dtype(
    [
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("index", "<i8"),  # point index within its tile (file order)
        ("tile", "<u2"),
        ("core", "u1"),  # 1 in this block's core, 0 halo, 2 shadow (mixed step only)
        ("return_number", "u1"),
        ("number_of_returns", "u1"),
        ("scan_id", "<u2"),
        ("classification", "u1"),  # the input's class (kept classes)
    ]
)
#: Shards of ground-based jobs also carry each point's GPS time (NaN where the file has
#: none), which places a return on its beam by firing order; a folder written so holds
#: the ``TIMED_FILE`` marker.
SHARD_DTYPE_TIMED = np.dtype(SHARD_DTYPE.descr + [("gps_time", "<f8")])
TIMED_FILE = "gps_time"


def shard_dtype(shard_dir: Path) -> np.dtype:
    """The record type of the shards in ``shard_dir`` (timed or not, by its marker)."""
    return SHARD_DTYPE_TIMED if (Path(shard_dir) / TIMED_FILE).exists() else SHARD_DTYPE


@dataclass(frozen=True)
class BlockGrid:
    """Block layout and the job raster it is snapped to.

    ``x0, y0`` is the raster's lower-left corner; the raster is ``width`` ×
    ``height`` cells of ``resolution``. Block (ix, iy) has its core at
    [x0 + ix·B, x0 + (ix+1)·B) × [y0 + iy·B, y0 + (iy+1)·B), clipped to the raster.
    """

    x0: float
    y0: float
    resolution: float
    width: int
    height: int
    block_size: float
    buffer: float

    @classmethod
    def over(
        cls,
        mins: tuple[float, float],
        maxs: tuple[float, float],
        resolution: float,
        block_size: float,
        buffer: float,
        align: float | None = None,
    ) -> BlockGrid:
        """The grid covering [mins, maxs].

        Its corner, its size and the block size are multiples of ``align``
        metres (itself a multiple of ``resolution``), so coarser grids laid on
        the same origin (vegetation bins, 2 m category tiles) fit it exactly.
        """
        k = max(1, int(round((align or resolution) / resolution)))
        step = k * resolution
        block_cells = k * max(1, int(round(block_size / step)))
        x0 = float(np.floor(mins[0] / step) * step)
        y0 = float(np.floor(mins[1] / step) * step)
        width = k * (int(np.floor((maxs[0] - x0) / step)) + 1)
        height = k * (int(np.floor((maxs[1] - y0) / step)) + 1)
        return cls(x0, y0, resolution, width, height, block_cells * resolution, buffer)

    @property
    def block_cells(self) -> int:
        return int(round(self.block_size / self.resolution))

    @property
    def nx(self) -> int:
        return -(-self.width // self.block_cells)

    @property
    def ny(self) -> int:
        return -(-self.height // self.block_cells)

    @property
    def y_top(self) -> float:
        return self.y0 + self.height * self.resolution

    def to_dict(self) -> dict:
        return asdict(self)

    def block_of(self, x: NDArray, y: NDArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Core block column and row of each point (clipped into the grid)."""
        ix = np.floor((x - self.x0) / self.block_size).astype(np.int64)
        iy = np.floor((y - self.y0) / self.block_size).astype(np.int64)
        return np.clip(ix, 0, self.nx - 1), np.clip(iy, 0, self.ny - 1)

    def blocks_over(self, mins: Sequence[float], maxs: Sequence[float]) -> set[tuple[int, int]]:
        """The (ix, iy) of every block whose core may hold a point of the box
        [mins, maxs]: a tile's blocks, so its classified copy reads only those."""
        ix, iy = self.block_of(np.array([mins[0], maxs[0]]), np.array([mins[1], maxs[1]]))
        return {
            (i, j)
            for i in range(int(ix[0]), int(ix[1]) + 1)
            for j in range(int(iy[0]), int(iy[1]) + 1)
        }

    def core_window(self, ix: int, iy: int) -> tuple[int, int, int, int]:
        """(row_off, col_off, rows, cols) of block (ix, iy) in the north-up job raster."""
        c = self.block_cells
        col0 = ix * c
        cols = min(c, self.width - col0)
        row_bottom = self.height - iy * c  # exclusive, counted from the top
        rows = min(c, row_bottom)
        return row_bottom - rows, col0, rows, cols

    def core_bounds(self, ix: int, iy: int) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the block core, clipped to the raster."""
        row_off, col_off, rows, cols = self.core_window(ix, iy)
        xmin = self.x0 + col_off * self.resolution
        ymax = self.y_top - row_off * self.resolution
        return xmin, ymax - rows * self.resolution, xmin + cols * self.resolution, ymax


def block_name(ix: int, iy: int) -> str:
    return f"{ix}_{iy}"


def parse_block_name(name: str) -> tuple[int, int]:
    a, b = name.split("_")
    return int(a), int(b)


def assign_blocks(
    grid: BlockGrid, x: NDArray, y: NDArray
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    """(point index, flat block id, is-core) for every block each point goes to.

    A point goes to its core block and to each neighbour (8-connected) whose
    core is within ``buffer`` of it. Every point is in its core block; only the
    points within ``buffer`` of their core's edge are tested for neighbours.
    """
    ix, iy = grid.block_of(x, y)
    fx = x - (grid.x0 + ix * grid.block_size)
    fy = y - (grid.y0 + iy * grid.block_size)
    b, far = grid.buffer, grid.block_size - grid.buffer
    out_p = [np.arange(x.size)]
    out_b = [iy * grid.nx + ix]
    edge = np.flatnonzero((fx < b) | (fx >= far) | (fy < b) | (fy >= far))
    ex, ey, fx, fy = ix[edge], iy[edge], fx[edge], fy[edge]
    for dx in (-1, 0, 1):
        mx = np.ones(edge.size, bool) if dx == 0 else (fx < b if dx < 0 else fx >= far)
        mx &= (ex + dx >= 0) & (ex + dx < grid.nx)
        for dy in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            my = np.ones(edge.size, bool) if dy == 0 else (fy < b if dy < 0 else fy >= far)
            m = np.flatnonzero(mx & my & (ey + dy >= 0) & (ey + dy < grid.ny))
            out_p.append(edge[m])
            out_b.append((ey[m] + dy) * grid.nx + (ex[m] + dx))
    core = np.zeros(sum(a.size for a in out_p), dtype=bool)
    core[: x.size] = True
    return np.concatenate(out_p), np.concatenate(out_b), core


def scan_reach(
    tile_path: str,
    origins: Sequence[Sequence[float]],
    scan_dim: str | None = None,
    start: int = 0,
    stop: int | None = None,
    roots: Sequence[str] | None = None,
    chunk_size: int = 1_000_000,
) -> list[float]:
    """Per scan position (numbered by the points' scan ids), the horizontal distance of
    its farthest return among the tile's points ``start``..``stop`` (0 where none): no
    return lies farther along any of its rays, so ``assign_shadow`` stops there."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(o.shape[0])
    for chunk in iter_chunks(tile_path, chunk_size, scan_dim, start, stop, roots):
        sid = chunk.scan_id.astype(np.int64) if o.shape[0] > 1 else np.zeros(len(chunk.xyz), int)
        has = sid < o.shape[0]
        sid = sid[has]
        d = np.hypot(chunk.xyz[has, 0] - o[sid, 0], chunk.xyz[has, 1] - o[sid, 1])
        np.maximum.at(out, sid, d)
    return [float(v) for v in out]


def assign_shadow(
    grid: BlockGrid,
    x: NDArray,
    y: NDArray,
    ox: NDArray,
    oy: NDArray,
    own: tuple[NDArray[np.int64], NDArray[np.int64]],
    reach: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(point index, flat block id) of the blocks each point's ray passes through beyond
    the point (from its sensor at ``ox, oy``), other than those in ``own`` (the point's
    core and halo blocks, from ``assign_blocks``).

    A ground-based scan's neighbouring beams may return from anywhere along their rays:
    an occluder's edge in front of a block is a neighbour of the background returns in
    it, though metres outside its halo. The ray is followed in steps of the halo (at
    most half a block), each step copied to the blocks within the halo of it, so a
    block gets every return whose ray continues within the halo of its core. The ray
    ends at the grid's edge or, with ``reach`` (per point: the horizontal distance of
    its scan position's farthest return, ``scan_reach``), where no return lies beyond.
    """
    dx, dy = x - ox, y - oy
    d = np.hypot(dx, dy)
    ok = d > 1e-6
    ux = np.where(ok, dx / np.where(ok, d, 1.0), 0.0)
    uy = np.where(ok, dy / np.where(ok, d, 1.0), 0.0)
    x1 = grid.x0 + grid.width * grid.resolution
    y1 = grid.y0 + grid.height * grid.resolution
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(ux > 0, (x1 - x) / ux, np.where(ux < 0, (grid.x0 - x) / ux, np.inf))
        ty = np.where(uy > 0, (y1 - y) / uy, np.where(uy < 0, (grid.y0 - y) / uy, np.inf))
    t_exit = np.where(ok, np.maximum(np.minimum(tx, ty), 0.0), 0.0)
    if reach is not None:
        t_exit = np.minimum(t_exit, np.maximum(reach - d, 0.0))
    step = min(grid.buffer, grid.block_size / 2) if grid.buffer > 0 else grid.block_size / 4
    n = np.ceil(t_exit / step).astype(np.int64)
    if n.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rep = np.repeat(np.arange(x.size), n)
    k = np.arange(rep.size) - np.repeat(np.cumsum(n) - n, n) + 1  # 1..n per point
    t = np.minimum(k * step, t_exit[rep])
    p, bid, _ = assign_blocks(grid, x[rep] + ux[rep] * t, y[rep] + uy[rep] * t)
    nb = grid.nx * grid.ny
    key = _sorted_unique(rep[p] * nb + bid)
    key = key[~np.isin(key, own[0] * nb + own[1])]
    return key // nb, key % nb


#: file of a shard folder holding the occupied cells of its points (``occupied_cells``)
OCCUPANCY_FILE = "occupancy.npy"


def occupancy_cell(density: float) -> float:
    """Cell size for measuring occupied area: two mean spacings at ``density``
    (about four points per occupied cell, as ``ground.nist``'s own measure)."""
    return 2.0 / float(np.sqrt(max(density, 1e-9)))


def occupied_cells(x: NDArray, y: NDArray, cell: float) -> NDArray[np.int64]:
    """Sorted unique keys of the ``cell``-sized squares, anchored on absolute
    multiples of ``cell``, that hold at least one of the points."""
    if np.size(x) == 0:
        return np.zeros(0, np.int64)
    ix = np.floor(np.asarray(x) / cell).astype(np.int64)
    iy = np.floor(np.asarray(y) / cell).astype(np.int64)
    x0, y0 = int(ix.min()), int(iy.min())
    nx, ny = int(ix.max()) - x0 + 1, int(iy.max()) - y0 + 1
    if nx * ny > max(4 * ix.size, 1 << 16):  # scattered points: sort them
        return _sorted_unique((ix << 32) ^ (iy & 0xFFFFFFFF))
    # A flag per cell of the points' bounding box: linear, several times faster than sorting.
    flags = np.zeros(nx * ny, dtype=bool)
    flags[(ix - x0) * ny + (iy - y0)] = True
    f = np.flatnonzero(flags)
    return np.sort(((f // ny + x0) << 32) ^ ((f % ny + y0) & 0xFFFFFFFF))


def occupied_density(points: int, keys: Sequence[NDArray[np.int64]], cell: float) -> float:
    """Points per m² over the union of the occupied cells in ``keys`` (parts of
    one job may share cells: overlapping tiles, parts of one tile)."""
    merged = _sorted_unique(np.concatenate(list(keys))) if keys else np.zeros(0, np.int64)
    return points / max(merged.size * cell * cell, 1e-9)


def _sorted_unique(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """``np.unique(keys)`` by one sort: numpy's hashing unique of int64 keys
    profiled many times slower while sharding."""
    k = np.sort(keys)
    return k[np.r_[True, k[1:] != k[:-1]]] if k.size else k


def shard_tile(
    tile_path: str,
    tile_index: int,
    grid: BlockGrid,
    out_dir: str | Path,
    chunk_size: int = 1_000_000,
    scan_dim: str | None = None,
    start: int = 0,
    stop: int | None = None,
    roots: Sequence[str] | None = None,
    occupancy: float = 0.0,
    gps_time: bool = False,
    origins: Sequence[Sequence[float]] | None = None,
    reach: Sequence[float] | None = None,
) -> dict[str, int]:
    """Stream one tile (or its points ``start``..``stop``) into per-block shard
    files ``out_dir/<block>.bin``; with ``roots`` the tile must lie inside one
    of them when it is opened (``open_input``). With ``occupancy`` (a cell size),
    the cells the points occupy go to ``out_dir/occupancy.npy`` (``occupied_cells``).
    With ``gps_time`` the records are ``SHARD_DTYPE_TIMED`` (ground-based jobs). With
    the scan positions' ``origins`` (numbered by the points' scan ids) each point is also
    copied, with core 2, to the blocks its ray passes through beyond it
    (``assign_shadow``): for the mixed-measurement step only, up to the position's
    ``reach`` when given (``scan_reach`` over the whole job), else to the grid's edge.

    Writes into a temporary sibling folder and renames it when complete, so a
    crash leaves no half-written shard set. Returns core point counts per block.
    """
    core_counts: dict[str, int] = {}
    cells: list[NDArray[np.int64]] = []
    with atomic_path(out_dir) as tmp:
        tmp.mkdir()
        dtype = SHARD_DTYPE_TIMED if gps_time else SHARD_DTYPE
        if gps_time:
            (tmp / TIMED_FILE).touch()
        for chunk in iter_chunks(tile_path, chunk_size, scan_dim, start, stop, roots, gps_time):
            x, y = chunk.xyz[:, 0], chunk.xyz[:, 1]
            if occupancy > 0:
                cells.append(occupied_cells(x, y, occupancy))
            p, bid, core = assign_blocks(grid, x, y)
            core = core.astype(np.uint8)
            if origins is not None and len(origins) > 0:
                o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
                sid = chunk.scan_id.astype(np.int64) if o.shape[0] > 1 else np.zeros(x.size, int)
                has = sid < o.shape[0]
                sid = np.where(has, sid, 0)
                lim = None if reach is None else np.asarray(reach, dtype=np.float64)[sid]
                sp, sb = assign_shadow(grid, x, y, o[sid, 0], o[sid, 1], (p, bid), lim)
                keep = has[sp]
                p = np.concatenate([p, sp[keep]])
                bid = np.concatenate([bid, sb[keep]])
                core = np.concatenate([core, np.full(np.count_nonzero(keep), 2, np.uint8)])
            # Stable, so a block's points keep file order; on 16-bit ids numpy
            # sorts by radix (~6x faster than the merge sort of wider ints).
            key = bid.astype(np.uint16) if grid.nx * grid.ny <= 1 << 16 else bid
            order = np.argsort(key, kind="stable")
            p, bid, core = p[order], bid[order], core[order]
            rec = np.empty(p.size, dtype)
            if gps_time:
                rec["gps_time"] = np.nan if chunk.gps_time is None else chunk.gps_time[p]
            rec["x"], rec["y"], rec["z"] = x[p], y[p], chunk.xyz[p, 2]
            rec["index"] = chunk.start + p
            rec["tile"] = tile_index
            rec["core"] = core
            rec["return_number"] = chunk.return_number[p]
            rec["number_of_returns"] = chunk.number_of_returns[p]
            rec["scan_id"] = chunk.scan_id[p]
            rec["classification"] = 0 if chunk.classification is None else chunk.classification[p]
            starts = np.flatnonzero(np.r_[True, bid[1:] != bid[:-1]])
            ends = np.r_[starts[1:], bid.size]
            for s, e in zip(starts, ends, strict=True):
                b = int(bid[s])
                name = block_name(b % grid.nx, b // grid.nx)
                with open(tmp / f"{name}.bin", "ab") as fh:
                    rec[s:e].tofile(fh)
                core_counts[name] = core_counts.get(name, 0) + int(np.count_nonzero(core[s:e] == 1))
        if occupancy > 0:
            merged = _sorted_unique(np.concatenate(cells)) if cells else np.zeros(0, np.int64)
            np.save(tmp / OCCUPANCY_FILE, merged)
    return core_counts


@dataclass(frozen=True)
class ShardPart:
    """A run of one tile's points, sharded by one task into ``shards/<name>``."""

    tile: int
    start: int
    stop: int

    @property
    def name(self) -> str:
        return f"{self.tile}-{self.start}"


def shard_parts(point_counts: list[int], part_points: int = 2_500_000) -> list[ShardPart]:
    """Split each tile into about equal runs of roughly ``part_points`` points.

    A large tile is sharded by several tasks at once (LAZ readers seek through
    the chunk table), so a one-tile job does not wait on one reader.
    """
    parts = []
    for tile, n in enumerate(point_counts):
        k = max(1, int(round(n / part_points)))
        bounds = [n * i // k for i in range(k + 1)]
        parts += [
            ShardPart(tile, a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a
        ]
    return parts


def read_block_points(shard_dirs: list[Path], name: str) -> NDArray:
    """All shard records of block ``name`` over every tile, as one structured array."""
    parts = [
        np.fromfile(d / f"{name}.bin", dtype=shard_dtype(d))
        for d in shard_dirs
        if (d / f"{name}.bin").exists()
    ]
    if not parts:
        return np.empty(0, shard_dtype(shard_dirs[0]) if shard_dirs else SHARD_DTYPE)
    return np.concatenate(parts)
