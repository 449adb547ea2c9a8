"""Low flat objects told from terrain by their edges, after the NIST passes.

Walled plateaus (``walled_plateaus``). Growth (``growth.py``) continues the
ground surface along each ground node's slope. A slope fitted from a couple
of close, noisy neighbours at the foot of a platform or a row of wagons can
predict the object's top; once one top node is ground, growth spreads over
the whole top. What still tells such a top from terrain is its edge: the top
is level, and wherever it meets the rest of the ground it drops straight
down, by the object's height, onto the terrain at its foot (nodes the passes
found, or nodes with no ground a step below them): no ground at intermediate
heights lies between. A crest or hilltop that growth recovers is reached the
other way: through grown nodes on its sides, each a step above the next, and
it has ground neighbours about as high as itself along it. So grown nodes are
grouped by level edges (within ``margin``); a group whose edges to ground
outside it are, for at least ``share`` of them, drops of ``step`` or more onto
the foot, and no more than the rest of them held (a neighbour less than
``margin`` below), is dropped as a whole, whatever its size.

Walled islands (``walled_islands``): a pitched roof reaches the final TIN as
rows of vertices, each row a step above the next, so ``raised.py`` cuts it
into segments none of which is raised on its own. Taken together where they
touch, they stand on walls above the terrain all round.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay

from terrasift.workers.ground.raised import (
    _along_edge,
    _median_per_vertex,
    data_border,
    tin_edges,
)


def walled_plateaus(
    z: NDArray[np.float64],
    ground: NDArray[np.bool_],
    seed: NDArray[np.bool_],
    adjacency: tuple[NDArray[np.int64], NDArray[np.int64]],
    *,
    margin: float,
    step: float,
    share: float,
) -> NDArray[np.bool_]:
    """Grown nodes (``ground`` and not ``seed``) in walled plateaus; see the module doc.

    ``z``: node heights; ``adjacency``: CSR (indptr, indices) of the node TIN.
    """
    n = z.size
    indptr, nbr = adjacency
    own = np.repeat(np.arange(n), np.diff(indptr))
    dz = z[nbr] - z[own]
    grown = ground & ~seed
    if not grown.any():
        return np.zeros(n, dtype=bool)
    level = grown[own] & grown[nbr] & (np.abs(dz) <= margin)
    _, group = connected_components(
        coo_matrix((np.ones(np.count_nonzero(level)), (own[level], nbr[level])), shape=(n, n)),
        directed=False,
    )
    # Edges from a grown node to ground outside its group.
    out = grown[own] & ground[nbr] & ((group[own] != group[nbr]) | ~grown[nbr])
    g = group[own[out]]
    n_out = np.bincount(g, minlength=n)
    held = np.bincount(g, weights=dz[out] >= -margin, minlength=n) > (1.0 - share) * n_out
    # A drop is a wall when it lands on the terrain at the object's foot: a seed, or a
    # ground node with no ground neighbour a step lower (not partway down a slope).
    ge = ground[own] & ground[nbr]
    low = np.bincount(own[ge], weights=dz[ge] <= -step, minlength=n) > 0
    foot = seed | (ground & ~low)
    walls = np.bincount(g, weights=foot[nbr[out]] & (dz[out] <= -step), minlength=n)
    flagged = (n_out > 0) & ~held & (walls >= share * n_out)
    return grown & flagged[group]


def walled_islands(
    xyz: NDArray[np.float64],
    tri: Delaunay,
    gone: NDArray[np.bool_],
    step: float,
    step_slope_deg: float,
    *,
    walls: float,
    edge: float,
    cut: tuple[float, float, float, float] | None = None,
) -> NDArray[np.bool_]:
    """Vertices of ``tri`` (on ``xyz[:, :2]``) in walled islands, beside ``gone`` (dropped already).

    The TIN is cut into segments along steps as ``raised.py`` does (edges rising
    ``step`` or more, steeper than ``step_slope_deg``). A pitched roof is cut into
    a row of segments, each the upper side of the steps below it and the lower
    side of those above, so no single one is raised. Taken together, every segment
    but the largest (the terrain) and those already gone forms islands: connected
    parts of the TIN. An island whose every edge to the terrain segment rises a
    step onto it, at least ``walls`` of them walls against the terrain at their
    foot, whose border steps rise (median) by at least half its mean height above
    their feet, and that does not reach the edge of the data along ``edge`` metres
    (a plateau crossing the data), stands above the terrain all round on walls and
    goes. A steep hill cut into rings by its slope edges climbs from its foot one
    ring at a time and stays. ``cut``: the box the points were cut to (a block's core
    and halo), whose sides are not the edge of the data (``raised.raised_segments``).
    """
    n = xyz.shape[0]
    e = tin_edges(tri)
    dz = xyz[e[:, 1], 2] - xyz[e[:, 0], 2]
    run = np.hypot(*(xyz[e[:, 1], :2] - xyz[e[:, 0], :2]).T)
    grad = np.abs(dz) / np.maximum(run, 1e-9)
    tan_step = np.tan(np.radians(step_slope_deg))
    is_step = (np.abs(dz) >= step) & (grad >= tan_step)
    gentle = e[~is_step]
    _, seg = connected_components(
        coo_matrix((np.ones(gentle.shape[0]), (gentle[:, 0], gentle[:, 1])), shape=(n, n)),
        directed=False,
    )
    size = np.bincount(seg[~gone]) if (~gone).any() else np.zeros(1, dtype=np.int64)
    terrain = seg == int(np.argmax(size))
    cand = ~terrain & ~gone
    if not cand.any():
        return np.zeros(n, dtype=bool)
    inner = e[cand[e[:, 0]] & cand[e[:, 1]]]
    _, island = connected_components(
        coo_matrix((np.ones(inner.shape[0]), (inner[:, 0], inner[:, 1])), shape=(n, n)),
        directed=False,
    )
    # Edges between an island vertex and the terrain segment, seen from the island.
    a_in = cand[e[:, 0]] & terrain[e[:, 1]]
    b_in = cand[e[:, 1]] & terrain[e[:, 0]]
    border = a_in | b_in
    isl = np.where(a_in, island[e[:, 0]], island[e[:, 1]])[border]
    rise = np.where(a_in, -dz, dz)[border]  # island end above the terrain end
    # Wall: steeper than the terrain at its foot (median gradient of the edges going down from it).
    upper = np.where(dz > 0, e[:, 1], e[:, 0])
    base = _median_per_vertex(upper, grad, n)
    lower = np.where(dz > 0, e[:, 0], e[:, 1])
    wall = (grad - base[lower] >= tan_step)[border]
    up = is_step[border] & (rise > 0)
    k = int(island.max()) + 1
    n_border = np.bincount(isl, minlength=k)
    n_up = np.bincount(isl, weights=up, minlength=k)
    n_wall = np.bincount(isl, weights=up & wall, minlength=k)
    raised = (n_border > 0) & (n_up == n_border) & (n_wall >= walls * n_up)
    # Most of its height is in the wall: the median rise of its border steps is at
    # least half its mean height above their feet. A steep hill whose slope edges
    # cut it into rings climbs from its foot one ring at a time.
    foot = np.where(a_in, e[:, 1], e[:, 0])[border]
    n_isl = np.maximum(np.bincount(island, minlength=k), 1)
    mean_z = np.bincount(island, weights=xyz[:, 2], minlength=k) / n_isl
    foot_z = np.bincount(isl, weights=xyz[foot, 2], minlength=k) / np.maximum(n_border, 1)
    raised &= _median_per_vertex(isl, rise, k) >= 0.5 * (mean_z - foot_z)
    if edge > 0 and raised.any():
        med = float(np.median(run))
        border = None if cut is None else data_border(xyz[:, :2], tri, cut, med)
        raised &= _along_edge(xyz[:, :2], tri, island, k, med, border) < edge
    return cand & raised[island]
