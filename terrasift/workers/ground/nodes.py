"""Ground nodes chosen by a rule of the data: the lowest point of the square around it.

Binning picks the lowest point of each bin, so which points become nodes moves
with where the bins fall: a translation of a few metres, or another tile origin,
puts other points at the bottom of the bins (on sparse data a final bin holds a
couple of points). Here a point is a node when it is the lowest (about the
least-squares plane of the ``cell``-sized square centred on it, level where
fewer than four points or collinear ones give no plane) of the points in that
square. The rule looks only at the points around each one, so the node set
moves with the data and not with the origin; its density is about one node per
``cell`` square, as the bins'.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.workers.bins import planes_from_sums


def square_lowest(
    xyz: NDArray[np.float64], cell: float, z_tol: float = np.inf
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Indices of the points of ``xyz`` lowest in the ``cell`` square centred on them
    (see the module doc), and per such node the gradient (dz/dx, dz/dy) of that
    square's plane (0 where there is none). A square whose RMS about its plane
    exceeds ``z_tol`` gives no node (select/reject's RMS test)."""
    n = xyz.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    pairs = cKDTree(xyz[:, :2]).query_pairs(0.5 * cell, p=np.inf, output_type="ndarray")
    own = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    nbr = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    u = xyz[nbr, 0] - xyz[own, 0]
    v = xyz[nbr, 1] - xyz[own, 1]
    w = xyz[nbr, 2] - xyz[own, 2]

    def s(a: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.bincount(own, weights=a, minlength=n).astype(np.float64)

    # Normal equations of w = c + sx u + sy v over the square (the point itself at 0, 0, 0).
    nf = 1.0 + np.bincount(own, minlength=n).astype(np.float64)
    sums = np.stack([s(a) for a in (u, v, w, u * u, v * v, u * v, u * w, v * w)])
    # Four points at least: a plane through three fits them all exactly, and which is
    # lowest would be rounding.
    ok, c, sx, sy = planes_from_sums(nf, sums, cell, min_n=4)
    c, sx, sy = (np.where(ok, a, 0.0) for a in (c, sx, sy))
    # Residuals about the square's plane (about the point's own height where none).
    res_nbr = w - c[own] - sx[own] * u - sy[own] * v
    res_self = -c
    lowest_other = np.full(n, np.inf)
    np.minimum.at(lowest_other, own, res_nbr)
    ss = res_self**2 + s(res_nbr**2)
    node = (res_self <= lowest_other) & (np.sqrt(ss / nf) <= z_tol)
    idx = np.flatnonzero(node)
    return idx, np.column_stack([sx[idx], sy[idx]])
