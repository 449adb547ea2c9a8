"""Raised segments of a ground TIN: parts that stand above the rest behind steps.

A roof or a bridge deck wide enough to fill the bins of every pass reaches the
ground TIN as a patch of well-behaved vertices: flat, screened as smooth, not
mowed. What gives it away is its border: everywhere it meets the rest of the
TIN, the TIN drops by a wall (an edge rising at least ``step`` metres, steeper
than ``step_slope``), while terrain joins its surroundings somewhere without
one. So the TIN is cut into segments along step edges, and a segment that is
only ever the upper side of its steps is dropped as a whole. Segments on the
block's hull are kept (what lies beyond is unknown), and so is the largest.
Repeated, so a roof under a raised part (a tower) goes too.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay


def tin_edges(tri: Delaunay) -> NDArray[np.int64]:
    """Unique undirected edges (i < j) of a 2-D triangulation, shape (m, 2)."""
    indptr, indices = tri.vertex_neighbor_vertices
    owner = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    e = np.column_stack([owner, indices]).astype(np.int64)
    return e[e[:, 0] < e[:, 1]]


def raised_segments(
    xyz: NDArray[np.float64],
    tri: Delaunay,
    step: float,
    step_slope_deg: float,
    *,
    rounds: int = 4,
) -> NDArray[np.bool_]:
    """Vertices of ``tri`` (built on ``xyz[:, :2]``) in raised segments; see the module doc."""
    n = xyz.shape[0]
    e = tin_edges(tri)
    dz = xyz[e[:, 1], 2] - xyz[e[:, 0], 2]
    run = np.hypot(*(xyz[e[:, 1], :2] - xyz[e[:, 0], :2]).T)
    is_step = (np.abs(dz) >= step) & (np.abs(dz) >= np.tan(np.radians(step_slope_deg)) * run)
    gentle = e[~is_step]
    graph = coo_matrix((np.ones(gentle.shape[0]), (gentle[:, 0], gentle[:, 1])), shape=(n, n))
    n_seg, seg = connected_components(graph, directed=False)
    size = np.bincount(seg, minlength=n_seg)
    fixed = np.zeros(n_seg, dtype=bool)
    fixed[seg[np.unique(tri.convex_hull)]] = True
    fixed[np.argmax(size)] = True
    st = e[is_step]
    up = dz[is_step] > 0
    lo = np.where(up, st[:, 0], st[:, 1])
    hi = np.where(up, st[:, 1], st[:, 0])
    lo, hi = seg[lo], seg[hi]
    cross = lo != hi
    lo, hi = lo[cross], hi[cross]
    gone = np.zeros(n_seg, dtype=bool)
    for _ in range(rounds):
        live = ~gone[lo] & ~gone[hi]
        under = np.zeros(n_seg, dtype=bool)
        under[lo[live]] = True  # something stands on this segment
        raised = ~fixed & ~gone & ~under
        if not raised.any():
            break
        gone |= raised
    return gone[seg]
