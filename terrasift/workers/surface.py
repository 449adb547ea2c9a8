"""A ground surface through points: ``TinSurface``, linear on the Delaunay TIN of
the ground filters (``ground.tin.Tin``), the nearest vertex's height outside it.

Coordinates are shifted to a local origin before triangulating, because
projected coordinates (5e6 m) cost precision. Queries are located by the TIN's
compiled walk, fed in a serpentine spatial order (``spatial_order``) so each
walk is a step or two.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import QhullError, cKDTree

from terrasift.workers.ground.tin import Tin

#: points closer than this in x and y are one vertex, the lowest of them (metres)
COINCIDENT = 1e-3


def spatial_order(xy: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Serpentine row order of ``cell``-sized bins: consecutive points are close,
    which is what makes a walk from the last hit fast."""
    ix = np.floor((xy[:, 0] - xy[:, 0].min()) / cell).astype(np.int64)
    iy = np.floor((xy[:, 1] - xy[:, 1].min()) / cell).astype(np.int64)
    nx = int(ix.max()) + 1
    ix = np.where(iy % 2 == 1, nx - 1 - ix, ix)
    return np.argsort(iy * nx + ix)


class TinSurface:
    """z(x, y) linearly interpolated on the TIN of ``xyz``; nearest vertex outside the hull.

    Points closer than ``COINCIDENT`` in x, y keep the lowest; fewer than three
    distinct points, or collinear ones, give the nearest point's height everywhere.
    """

    def __init__(self, xyz: NDArray[np.float64]):
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.shape[0] == 0:
            raise ValueError("a surface needs at least one point")
        self.origin = xyz[:, :2].mean(axis=0)
        xy = xyz[:, :2] - self.origin
        keep = _lowest_of_coincident(xy, xyz[:, 2])
        self.xy = xy[keep]
        self.z = xyz[keep, 2]
        self._tin: Tin | None = None
        if self.xy.shape[0] >= 3:
            try:
                self._tin = Tin(
                    np.column_stack([self.xy, self.z]),
                    origin=np.zeros(2),
                    order=spatial_order(self.xy, _insertion_cell(self.xy)),
                )
            except (QhullError, ValueError):  # collinear
                self._tin = None
        self._kd: cKDTree | None = None

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        q = np.column_stack([np.ravel(x), np.ravel(y)]) - self.origin
        out = np.full(q.shape[0], np.nan)
        if self._tin is not None and q.shape[0]:
            order = spatial_order(q, 8.0)
            t, bary = self._tin.locate(q[order])
            hit = t >= 0
            corners = self._tin.simplices[t[hit]]
            out[order[hit]] = np.einsum("ni,ni->n", bary[hit], self.z[corners])
        outside = np.isnan(out)
        if outside.any():
            if self._kd is None:
                self._kd = cKDTree(self.xy)
            _, nearest = self._kd.query(q[outside])
            out[outside] = self.z[nearest]
        return out.reshape(np.shape(x))


def _insertion_cell(xy: NDArray[np.float64]) -> float:
    """Cells of about four vertices: inserted in serpentine order of these, each
    new vertex is a step or two from the last, and ties among co-circular
    vertices are broken the same way on every run."""
    area = max(float(np.prod(np.ptp(xy, axis=0))), 1e-6)
    return max(float(np.sqrt(4.0 * area / xy.shape[0])), 1e-3)


def _lowest_of_coincident(xy: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.int64]:
    """Indices, in point order, of the lowest point of each group of points
    chained closer than ``COINCIDENT`` in x, y (all points when none are)."""
    pairs = cKDTree(xy).query_pairs(COINCIDENT, output_type="ndarray")
    if pairs.shape[0] == 0:
        return np.arange(xy.shape[0])
    n = xy.shape[0]
    graph = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    o = np.lexsort((np.arange(n), z, group))
    g = group[o]
    return np.sort(o[np.r_[True, g[1:] != g[:-1]]])
