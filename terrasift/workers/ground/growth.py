"""Ground growth: recover terrain that coarse bins and mowing cut off.

Every pass of the NIST schedule meshes the lowest point of bins and mows what
stands above that mesh. A ridge, an embankment or a hilltop narrower than a
bin of the early passes loses its top there: the mesh spans it from foot to
foot, the top is mowed, and no later pass sees those points again (on the
ISPRS samples nearly all ground lost is above the final surface).

Growth puts them back by continuing the ground surface from its edge: nodes
are the lowest points of small bins, meshed once (Delaunay); nodes the
surface already labels ground are the seeds. In rounds, a node joins when a
ground neighbour, continued along its own slope (a least-squares plane
through its ground neighbours), predicts the node's height within ``tol`` +
tan(``bend``) × distance (``tol_below`` and ``bend_below`` in place of ``tol``
and ``bend`` for a node lower than predicted: objects stand above terrain, so
going down leads onto none, and over a crest the slope turns from rising to
falling within one edge, by more the further apart the nodes are).
The surface can thus follow a slope that bends gradually onto a hill, but
not jump onto a roof (a wall is a bend of ~90°), and a ground neighbour's
slope is only ever taken from ground.

A slope fitted from two or three close neighbours is noise: at the foot of a
platform, two ground nodes 0.5–0.9 m away and 0.07–0.10 m lower gave slopes of
0.2–0.5, which predicted the platform's top 2–3 m away within tolerance; once
one top node was ground, the foot nodes beside it fitted their slopes through
it and let in the next, and growth spread along the wall and over the top
(synthetic railway yards). With ``agree``, a node joins only when at least
that share of its ground neighbours predict it: the other foot nodes, fitted
on level ground, do not. Off by default: a dike crest of sparse data (ISPRS
samp61) is reached the same way, through a single ground neighbour.

Growth still steps onto small objects beside slopes (a bush, a car, a
shed, the edge of a hedge or a roof), where a ground neighbour's slope
happens to predict their height. Such nodes end up standing above all the
ground around them: a peak of the grown surface, or a small level group of
nodes. Terrain at the spacing of the nodes seldom has one (a crest has
neighbours along it at its own height), so a group of grown nodes that are
level with each other (within ``peak``), no more than ``peak_nodes`` of
them, standing more than ``peak`` above all its other ground neighbours is
dropped, repeatedly, until none is left; seeds stay.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError

from terrasift.workers.ground._kernels import _grow_rounds


def grow_ground(
    xyz: NDArray[np.float64],
    seed: NDArray[np.bool_],
    *,
    tol: float,
    bend_deg: float,
    max_rise: float,
    tol_below: float | None = None,
    bend_below_deg: float | None = None,
    max_rounds: int = 200,
    adjacency: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None,
    barred: NDArray[np.bool_] | None = None,
    peak: float | None = None,
    peak_nodes: int = 1,
    agree: float = 0.0,
    reach: float = 0.0,
) -> NDArray[np.bool_]:
    """Ground flags of the nodes ``xyz`` (n, 3) grown from ``seed``; see the module doc.

    ``max_rise`` bounds the rise of one edge (metres), whatever the slope.
    ``tol_below`` (default ``tol``) replaces ``tol`` for nodes lower than predicted,
    and ``bend_below_deg`` (default ``bend_deg``, never less) replaces ``bend_deg``.
    ``adjacency`` (CSR indptr, indices) is the Delaunay neighbourhood of the
    nodes when the caller has triangulated them already. ``barred`` nodes are
    never grown onto (objects judged already, such as raised roofs). With
    ``peak`` (metres), grown nodes that stand more than that above all their
    ground neighbours are dropped, and so are level groups of up to
    ``peak_nodes`` grown nodes that do (see the module doc). With ``agree``
    (0–1), a node joins only when at least that share of its ground neighbours
    predict it (see the module doc). With ``reach`` (metres, 0: none), a node joins
    only through an edge that ends at most that far from a seed along the path
    growth took (sum of edge lengths): what decides a node then lies within
    ``reach`` of it, so data cut off further away cannot change it.
    """
    n = xyz.shape[0]
    ground = seed.copy()
    if n < 4 or not seed.any() or seed.all():
        return ground
    if adjacency is None:
        try:
            adjacency = Delaunay(xyz[:, :2]).vertex_neighbor_vertices
        except QhullError:
            return ground
    indptr, nbr = adjacency
    own = np.repeat(np.arange(n), np.diff(indptr))
    du = xyz[nbr, 0] - xyz[own, 0]
    dv = xyz[nbr, 1] - xyz[own, 1]
    dz = xyz[nbr, 2] - xyz[own, 2]
    dist = np.hypot(du, dv)
    bend = np.tan(np.radians(bend_deg)) * dist
    limit = tol + bend
    # Going down, the slope may bend faster: over a crest it turns from rising
    # to falling within one edge, while objects stand above terrain.
    bend_below = (
        bend if bend_below_deg is None else np.tan(np.radians(max(bend_below_deg, bend_deg))) * dist
    )
    limit_below = (tol if tol_below is None else tol_below) + bend_below
    all_edges = (own, nbr, dz)
    # Edges that may ever carry growth: not a rise steeper than max_rise.
    usable = dz <= max_rise
    if barred is not None:
        usable &= ~barred[nbr]
    own, nbr, du, dv, dz = own[usable], nbr[usable], du[usable], dv[usable], dz[usable]
    limit, limit_below, dist = limit[usable], limit_below[usable], dist[usable]
    # Path length from a seed along the edges growth took (first arrival, shortest then).
    path = np.where(seed, 0.0, np.inf) if reach > 0 else np.zeros(0)
    if agree <= 0 and reach <= 0:
        # The same rounds compiled, each trying only the edges whose slopes changed.
        _grow_rounds(
            ground, own, nbr.astype(np.int64), du, dv, dz, limit, limit_below,
            np.asarray(indptr, dtype=np.int64), np.asarray(adjacency[1], dtype=np.int64),
            max_rounds,
        )  # fmt: skip
    else:
        for _ in range(max_rounds):
            gx, gy = _ground_slopes(ground, own, nbr, du, dv, dz, n)
            cand = ground[own] & ~ground[nbr]
            err = dz[cand] - gx[own[cand]] * du[cand] - gy[own[cand]] * dv[cand]
            ok = (err <= limit[cand]) & (err >= -limit_below[cand])
            if reach > 0:
                arrive = path[own[cand]] + dist[cand]
                ok &= arrive <= reach
                first = np.full(n, np.inf)
                np.minimum.at(first, nbr[cand][ok], arrive[ok])
            if agree > 0:
                votes = np.bincount(nbr[cand][ok], minlength=n)
                voters = np.bincount(nbr[cand], minlength=n)
                new = np.flatnonzero((votes > 0) & (votes >= agree * voters))
            else:
                new = nbr[cand][ok]
            if new.size == 0:
                break
            ground[new] = True
            if reach > 0:
                path[new] = first[new]
    if peak is not None:
        ground = _without_peaks(ground, seed, *all_edges, margin=peak, max_nodes=peak_nodes)
    return ground


def _without_peaks(
    ground: NDArray[np.bool_],
    seed: NDArray[np.bool_],
    own: NDArray[np.int64],
    nbr: NDArray[np.int64],
    dz: NDArray[np.float64],
    *,
    margin: float,
    max_nodes: int = 1,
) -> NDArray[np.bool_]:
    """``ground`` without level groups of at most ``max_nodes`` grown nodes that stand
    more than ``margin`` above all their other ground neighbours (edges ``own`` →
    ``nbr`` rising ``dz``), until none does."""
    n = ground.size
    ground = ground.copy()
    while True:
        grown = ground & ~seed
        # Groups: grown nodes joined by edges level within the margin.
        level = grown[own] & grown[nbr] & (np.abs(dz) <= margin)
        _, group = connected_components(
            coo_matrix((np.ones(np.count_nonzero(level)), (own[level], nbr[level])), shape=(n, n)),
            directed=False,
        )
        # A group is held by a ground neighbour outside it that is not lower by more than the margin.
        holds = (
            ground[own] & ground[nbr] & (dz >= -margin) & ((group[own] != group[nbr]) | ~grown[nbr])
        )
        held = np.zeros(n, dtype=bool)
        held[group[own[holds]]] = True
        small = np.bincount(group, minlength=n) <= max_nodes
        drop = grown & ~held[group] & small[group]
        if not drop.any():
            return ground
        ground &= ~drop


def _ground_slopes(
    ground: NDArray[np.bool_],
    own: NDArray[np.int64],
    nbr: NDArray[np.int64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    dz: NDArray[np.float64],
    n: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gradient of the plane through each ground node that best fits its ground
    neighbours (least squares on the height differences); 0 where underdetermined."""
    both = ground[own] & ground[nbr]
    o, u, v, w = own[both], du[both], dv[both], dz[both]

    def s(x: NDArray[np.float64]) -> NDArray:
        return np.bincount(o, weights=x, minlength=n)

    suu, svv, suv, suz, svz = s(u * u), s(v * v), s(u * v), s(u * w), s(v * w)
    det = suu * svv - suv * suv
    ok = det > 1e-6 * (suu + svv) ** 2
    safe = np.where(ok, det, 1.0)
    gx = np.where(ok, (suz * svv - svz * suv) / safe, 0.0)
    gy = np.where(ok, (svz * suu - suz * suv) / safe, 0.0)
    return gx, gy
