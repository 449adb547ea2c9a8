"""TIN masking (NIST §2, §3.1.1): a partial TIN marks "hot spots" of elevation change.

Greedy insertion puts the point of largest deviation from the current TIN in
next; stopped after a fraction of the points, it leaves small triangles where
the elevation varies a lot (trees, bushes, building edges) and large ones on
open ground. The vertices of the triangles whose edges are all shorter than
``edge`` are the mask points; a bin holding one is rejected.

Insertion is batched: each round every triangle takes in its three worst
points, then the TIN is rebuilt. The vertex count grows about sevenfold per
round, so five or six rounds reach 10–15 % of a block. In the last round only the globally worst of
the per-triangle candidates go in, so the stop is exact.

Two insertion rules, as the paper offers: ``"deviation"`` (largest |dz|,
aggressive refinement at hot spots: the one used for masking) and ``"area"``
(|dz| × area of the triangle the point falls in: more even triangle sizes).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import QhullError

from terrasift.workers.bins import bounds
from terrasift.workers.ground._kernels import _extremes, _top_k_per_group
from terrasift.workers.ground.tin import Tin


def extremes_per_cell(xyz: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Indices of the lowest and the highest point of every ``cell``-sized square.

    The points a largest-deviation insertion picks first are a cell's extremes,
    so masking can run on them alone when a block is dense. Cells are counted
    from the smallest x and y; two compiled passes (``_extremes``).
    """
    x, y, z = (np.asarray(xyz[:, k], dtype=np.float64) for k in range(3))
    x0, x1, y0, y1 = (float(v) for v in bounds(x, y))
    # floor((x - x0) / cell) is monotone in x: the largest comes from the largest x.
    nx = int(np.floor((x1 - x0) / cell)) + 1
    ny = int(np.floor((y1 - y0) / cell)) + 1
    return _extremes(x, y, z, x0, y0, float(cell), nx, ny)


def partial_tin(
    xyz: NDArray[np.float64],
    fraction: float,
    rule: Literal["deviation", "area"] = "deviation",
    per_round: int = 3,
) -> tuple[Tin, NDArray[np.int64]]:
    """Greedy partial TIN over ``xyz`` stopped at ``fraction`` of the points.

    Each round inserts the ``per_round`` worst points of every triangle.
    Returns the TIN and the indices (into ``xyz``) of its vertices.
    """
    n = xyz.shape[0]
    target = max(4, int(round(fraction * n)))
    origin = xyz[:, :2].mean(axis=0)
    xy = xyz[:, :2] - origin
    # Start from the points nearest the corners of the bounding box.
    x, y = xy[:, 0], xy[:, 1]
    corners = [(x.min(), y.min()), (x.max(), y.min()), (x.max(), y.max()), (x.min(), y.max())]
    start = np.unique([int(np.argmin((x - cx) ** 2 + (y - cy) ** 2)) for cx, cy in corners])
    inserted = np.zeros(n, dtype=bool)
    inserted[start] = True
    while True:
        verts = np.flatnonzero(inserted)
        # Pools of extremes hold coincident points (the lowest and highest of a
        # cell at one position, as with several returns of one pulse).
        tin = Tin(np.take(xyz, verts, axis=0), origin=origin, coincident=True)
        if verts.size >= target:
            return tin, verts
        rest = np.flatnonzero(~inserted)
        if rest.size == 0:
            return tin, verts
        # np.take: several times faster than fancy indexing of rows, same values.
        ti, surf = tin.linear(np.take(xy, rest, axis=0))
        score = np.abs(xyz[rest, 2] - surf)
        if rule == "area":
            score = score * _areas(tin)[ti]
        winners = _worst_per_triangle(ti, score, tin.tri.simplices.shape[0], per_round)
        if winners.size == 0:
            return tin, verts
        room = target - verts.size
        if winners.size > room:
            winners = winners[np.argsort(-score[winners], kind="stable")[:room]]
        inserted[rest[winners]] = True


def mask_points(
    xyz: NDArray[np.float64],
    fraction: float,
    edge: float,
    rule: Literal["deviation", "area"] = "deviation",
) -> NDArray[np.int64]:
    """Indices of the mask points of ``xyz``: vertices of partial-TIN triangles
    whose three edges are all shorter than ``edge``."""
    if xyz.shape[0] < 8:
        return np.zeros(0, dtype=np.int64)
    try:
        tin, verts = partial_tin(xyz, fraction, rule)
    except (ValueError, QhullError):  # collinear or coincident points: nothing to mask
        return np.zeros(0, dtype=np.int64)
    s = tin.tri.simplices
    p = tin.xy[s]
    e = np.stack(
        [
            np.hypot(*(p[:, 1] - p[:, 0]).T),
            np.hypot(*(p[:, 2] - p[:, 1]).T),
            np.hypot(*(p[:, 0] - p[:, 2]).T),
        ],
        axis=1,
    )
    small = (e < edge).all(axis=1)
    return verts[np.unique(s[small])]


def _worst_per_triangle(
    ti: NDArray[np.int64], score: NDArray[np.float64], n_tri: int, k: int
) -> NDArray[np.int64]:
    """Indices of the up-to-``k`` highest positive scores per triangle: the
    best of every triangle (by triangle), then the second best, and so on; ties
    go to the smaller index. One compiled pass keeping each triangle's top ``k``."""
    return _top_k_per_group(
        np.asarray(ti, dtype=np.int64), np.asarray(score, dtype=np.float64), n_tri, k
    )


def _areas(tin: Tin) -> NDArray[np.float64]:
    s = tin.tri.simplices
    p = tin.xy[s]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
