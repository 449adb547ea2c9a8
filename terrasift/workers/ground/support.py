"""Supported points: ground left above a TIN of bin minima, recovered point by point.

A TIN through the lowest points of bins a few metres apart cuts into every
convex break narrower than a bin or two: the crest of an embankment, a sharp
ridge, the upper edge of a terrace. The labels there come out patchy: points
near the TIN's vertices are in the ground band, points between them stand
above it, though they are ground as much as their neighbours. What shows it
is their neighbourhood: an object stands *on* the terrain, above the ground
around it, while a point that has two or more ground points of its ``k``
nearest (within ``radius``) at or above its own height is flanked by terrain,
not standing on it.

So a non-ground point joins the ground when it lies no higher than ``tol``
above the ``rank + 1``-th highest of its ``k`` nearest ground points within
``radius`` (``rank`` 1: the second highest, so one stray high neighbour is
not enough). Repeated for ``rounds``, so a crest is taken in from both sides.
Only points under the highest ground of the 3 × 3 cells of size ``radius``
around them can pass, so the k-nearest queries run on those alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.workers.bins import Grid
from terrasift.workers.ground._kernels import _flagged_in, _still_todo, _top_of_ground, _under_top


def supported_points(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    *,
    radius: float,
    eligible: NDArray[np.bool_] | None = None,
    k: int = 8,
    rank: int = 1,
    tol: float = 0.0,
    rounds: int = 2,
) -> NDArray[np.bool_]:
    """``ground`` with the supported points of ``xyz`` (n, 3) added; see the module doc.

    Only ``eligible`` points may join (default: every non-ground point); points
    below the ground, low outliers among them, are better left out.
    """
    out = ground.copy()
    if rounds < 1 or k <= rank or not out.any() or out.all():
        return out
    grid = Grid.covering(xyz[:, 0], xyz[:, 1], radius)
    cell = grid.index(xyz[:, 0], xyz[:, 1])
    zs = np.ascontiguousarray(xyz[:, 2], dtype=np.float64)
    may = ~out if eligible is None else eligible & ~out
    todo = may
    for _ in range(rounds):
        # Necessary condition: some ground point of the 3 x 3 cells is as high.
        top = _top_of_ground(cell, zs, out, grid.size)
        top = _max3x3(top.reshape(grid.ny, grid.nx)).ravel()
        cand = _under_top(todo, zs, top, cell, tol)
        if cand.size == 0:
            break
        # The tree holds only the ground of the 3 x 3 cells around candidates.
        busy = np.zeros(grid.size, dtype=bool)
        busy[cell[cand]] = True
        busy = _dilate(busy.reshape(grid.ny, grid.nx)).ravel()
        gi = _flagged_in(out, busy, cell)
        kk = min(k, gi.size)
        if kk <= rank:
            break
        d, j = cKDTree(xyz[gi, :2]).query(xyz[cand, :2], k=kk, distance_upper_bound=radius)
        d, j = d.reshape(cand.size, kk), j.reshape(cand.size, kk)
        z = np.where(np.isfinite(d), xyz[gi[np.minimum(j, gi.size - 1)], 2], -np.inf)
        level = -np.partition(-z, rank, axis=1)[:, rank]  # the (rank + 1)-th highest
        new = cand[xyz[cand, 2] <= level + tol]
        if new.size == 0:
            break
        out[new] = True
        # Only points near the new ones can gain support in the next round.
        near = np.zeros(grid.size, dtype=bool)
        near[cell[new]] = True
        near = _dilate(near.reshape(grid.ny, grid.nx)).ravel()
        todo = _still_todo(may, out, near, cell)
    return out


def _max3x3(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Maximum over the 3 x 3 neighbourhood of every cell of the 2-D array ``a``."""
    p = np.pad(a, 1, constant_values=-np.inf)
    ny, nx = a.shape
    out = np.full_like(a, -np.inf)
    for dy in range(3):
        for dx in range(3):
            np.maximum(out, p[dy : dy + ny, dx : dx + nx], out=out)
    return out


def _dilate(a: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Cells of the 2-D mask ``a`` and their 8 neighbours."""
    return _max3x3(a.astype(np.float64)) > 0
