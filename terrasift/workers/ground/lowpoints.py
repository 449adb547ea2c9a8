"""Isolated low points among the ground: multipath and other returns under the terrain.

A ground filter grown from cell minima takes a return a few metres under the
terrain as ground (it is the lowest point around, and a TIN through it still
meets the distance tests of its neighbours), and each one digs a pit into the
DTM. Real terrain, even a ditch or the foot of a wall, is a surface: a ground
point has other ground points at about its own height around it. So a ground
point is an isolated low point when, of the other ground points around it
(at least ``min_points`` of them, else the data is too sparse to judge), fewer
than ``support`` lie below it or less than ``depth`` above it: the terrain
around it is all metres higher. ASPRS class 7 (low point, noise).

Vectorised on a grid of ``radius`` cells: the ground points are sorted once by
(cell, height), and each candidate counts its 3 x 3 neighbourhood's points in
a height band with two binary searches per cell. Only the lowest ground point
of each ``candidate_cell`` is a candidate (the others stand on it), repeated
on the cells that lost their lowest point.

A return alone in a gap of the data (a strip without overlap, a void) has no
neighbourhood to judge it by, yet where the data is dense enough elsewhere
(``min_points`` expected around a point at the ground's mean density) it is
judged against the plane of its ``lone_k`` nearest ground points that are not
alone themselves (across the gap, from both sides): a low point when it lies
more than ``depth``, and more than 3 deviations of that plane, below it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from terrasift.workers.bins import Grid, lowest_per_bin
from terrasift.workers.registry import StageParams, register


class LowPointParams(StageParams):
    """Parameters of the isolated-low-point test on ground points."""

    depth: float = Field(1.0, gt=0.0, le=100.0)
    """Metres: the height band above a point in which its support must lie."""
    radius: float = Field(2.0, gt=0.0, le=50.0)
    """Metres: horizontal reach of the neighbourhood (a square of 3 x 3 cells of this size)."""
    support: int = Field(2, ge=0, le=1000)
    """Fewer other ground points than this below or within ``depth`` above a
    point make it isolated (a pair of outliers is caught, a cluster of three
    is kept). 0: off."""
    min_points: int = Field(8, ge=1, le=10_000)
    """Other ground points the neighbourhood needs before a point is judged:
    sparse data (ISPRS samp52/61, under 0.5 ground points per m²) cannot tell
    a hollow from a lone return."""
    candidate_cell: float = Field(1.0, gt=0.0, le=50.0)
    """Metres: only the lowest ground point per cell of this size is tested per round."""
    rounds: int = Field(3, ge=1, le=20)
    """Rounds: a cell whose lowest point was dropped tests its next-lowest."""
    lone: int = Field(3, ge=0, le=1000)
    """A ground point with fewer other ground points than this in its neighbourhood,
    where the ground's mean density puts ``min_points`` there, is judged against the
    plane of its ``lone_k`` nearest ground points that are not alone (module doc). 0: off."""
    lone_k: int = Field(16, ge=3, le=256)
    """Ground points in the plane a lone point is judged by."""


@register("ground.lowpoints", LowPointParams, "isolated low points among the ground (class 7)")
def isolated_low_points(
    xyz: NDArray[np.float64], is_ground: NDArray[np.bool_], params: LowPointParams
) -> NDArray[np.bool_]:
    """Mask of the ``is_ground`` points of ``xyz`` that are isolated low points."""
    out = np.zeros(xyz.shape[0], dtype=bool)
    g = np.flatnonzero(is_ground)
    if params.support == 0 or g.size < params.support + 2:
        return out
    pts = xyz[g]
    lo = pts.min(axis=0)
    local = pts - lo
    grid = Grid.covering(local[:, 0], local[:, 1], params.radius)
    cell = grid.index(local[:, 0], local[:, 1])
    # One sorted key: cell-major, then height (span > every height difference).
    span = float(np.ptp(local[:, 2])) + 4.0 * params.depth + 1.0
    key = cell * span + local[:, 2]
    sorted_key = np.sort(key)
    cell_start = np.searchsorted(sorted_key, np.arange(grid.size + 1) * span)
    cgrid = Grid.covering(local[:, 0], local[:, 1], params.candidate_cell)
    ccell = cgrid.index(local[:, 0], local[:, 1])
    alive = np.ones(g.size, dtype=bool)
    todo = np.ones(cgrid.size, dtype=bool)
    for _ in range(params.rounds):
        low = lowest_per_bin(np.where(alive & todo[ccell], ccell, -1), local[:, 2], cgrid.size)
        cand = low[low >= 0]
        if cand.size == 0:
            break
        # In key order, each offset's queries rise monotonically: searchsorted
        # then starts each search where the last ended.
        cand = cand[np.argsort(key[cand])]
        below, level, above = _neighbourhood_counts(
            local[cand], cell[cand], grid, sorted_key, cell_start, span, params.depth
        )
        # The point itself sits in its own band; points already dropped still
        # count (they are few, and lie below the surface anyway).
        others = below + level + above - 1
        lone = (others >= params.min_points) & (below + level - 1 < params.support)
        if not lone.any():
            break
        hit = cand[lone]
        alive[hit] = False
        todo[:] = False
        todo[ccell[hit]] = True
    if params.lone > 0:
        alive &= ~_lone_low(local, alive, cell, grid, sorted_key, cell_start, span, params)
    out[g[~alive]] = True
    return out


def _lone_low(
    local: NDArray[np.float64],
    alive: NDArray[np.bool_],
    cell: NDArray[np.int64],
    grid: Grid,
    sorted_key: NDArray,
    cell_start: NDArray[np.int64],
    span: float,
    params: LowPointParams,
) -> NDArray[np.bool_]:
    """Mask over ``local`` (ground points): the points alone in a gap of data dense
    enough elsewhere that lie under the plane of their ``lone_k`` nearest ground points
    not alone by more than ``max(depth, 3 x its deviation)`` (module doc)."""
    low = np.zeros(local.shape[0], dtype=bool)
    area = max(float(np.prod(np.ptp(local[:, :2], axis=0))), 1.0)
    if local.shape[0] / area * (3 * params.radius) ** 2 < params.min_points:
        return low  # sparse data: too few neighbours anywhere to tell a gap
    below, level, above = _neighbourhood_counts(
        local, cell, grid, sorted_key, cell_start, span, params.depth
    )
    alone = alive & (below + level + above - 1 < params.lone)
    support = np.flatnonzero(alive & ~alone)
    idx = np.flatnonzero(alone)
    if idx.size == 0 or support.size < params.lone_k:
        return low
    _, nb = cKDTree(local[support, :2]).query(local[idx, :2], k=params.lone_k)
    d = local[support[nb]] - local[idx][:, None, :]
    a = np.stack([np.ones(d.shape[:2]), d[..., 0], d[..., 1]], axis=-1)
    w = np.ones(d.shape[:2])
    for _ in range(2):  # fitted, then refitted without the neighbours far off it
        at = np.swapaxes(a * w[..., None], 1, 2)
        coef = np.linalg.solve(at @ a + 1e-9 * np.eye(3), at @ d[..., 2:3])[..., 0]
        res = d[..., 2] - np.einsum("mkp,mp->mk", a, coef)
        dev = np.sqrt(np.sum(w * res * res, axis=1) / np.maximum(np.sum(w, axis=1) - 3, 1))
        w = (np.abs(res) <= 2.5 * np.maximum(dev, 0.05 * params.depth)[:, None]).astype(float)
    # The point sits at the origin: the plane passes coef[0] above it.
    low[idx] = coef[:, 0] > np.maximum(params.depth, 3.0 * dev)
    return low


def _neighbourhood_counts(
    q: NDArray[np.float64],
    qcell: NDArray[np.int64],
    grid: Grid,
    sorted_key: NDArray,
    cell_start: NDArray[np.int64],
    span: float,
    depth: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Points of the 3 x 3 cells around each query below z, in [z, z + depth], and
    above; ``cell_start[c]`` is where cell ``c`` begins in ``sorted_key``."""
    iy, ix = np.divmod(qcell, grid.nx)
    below = np.zeros(q.shape[0], dtype=np.int64)
    level = np.zeros(q.shape[0], dtype=np.int64)
    above = np.zeros(q.shape[0], dtype=np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            jx, jy = ix + dx, iy + dy
            ok = (jx >= 0) & (jx < grid.nx) & (jy >= 0) & (jy < grid.ny)
            j = (jy * grid.nx + jx)[ok]
            base = j * span
            z = q[ok, 2]
            start, c = cell_start[j], cell_start[j + 1]
            a = np.searchsorted(sorted_key, base + z, side="left")
            b = np.searchsorted(sorted_key, base + z + depth, side="right")
            below[ok] += a - start
            level[ok] += b - a
            above[ok] += c - b
    return below, level, above
