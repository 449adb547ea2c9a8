"""A pit-free canopy height model from vegetation points: layered TINs.

A CHM gridded from the highest point per cell has pits: cells whose highest
return fell deep inside a crown (or on the ground through a gap) between
cells that caught the crown's top. The layered ("pit-free") method of
Khosravipour et al. (2014) triangulates, for each height threshold t of a
ladder (0, 2, 5, 10, 15, … m), only the returns at least t above ground, and
drops the triangles with an edge longer than ``max_edge`` (they would bridge
two crowns over a gap); the CHM is the highest layer at each cell. Layers
here are ``STEP`` (2 m) apart all the way up, where the paper widens them to
5 m above 5 m: a return inside the top layer of a crown dips it by less than
a step. Callers pass first returns where the data has returns (the paper's
choice): later returns are inside the crowns. A low
return between high ones is absent from the high layers, so it cannot dig a
pit; a real gap wider than ``max_edge`` stays open.

Each layer is triangulated by Qhull (``_triangulate``), not by the ground
filters' TIN (``ground.tin.Tin``): a layer is built once and only looked up,
and where points are co-circular the two break the tie differently.

Heights are above the ground surface; ground points enter the 0 layer at
height 0, so open ground reads 0 and a crown's edge falls to it. Cells farther
than the data reach are left to the caller's nodata mask.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError

from terrasift.workers.dem import Window
from terrasift.workers.surface import spatial_order

STEP = 2.0
"""Metres between the layers' thresholds: a return inside a crown can still dip
the highest layer that holds it, by less than one step."""


def max_edge_for(density: float, resolution: float) -> float:
    """Longest triangle edge kept in a layer: four point spacings at ``density``
    points per m², at least two cells (so a layer covers the cells between its points).

    On lidR MixedConifer (4.6 points/m², 0.5 m cells) three spacings left 0.7 %
    of canopy cells as pits, four 0.3 %; longer edges bridge more real gaps."""
    return float(max(4.0 / np.sqrt(max(density, 1e-6)), 2.0 * resolution))


def layered_chm(
    xy: NDArray[np.float64],
    height: NDArray[np.float64],
    window: Window,
    max_edge: float,
    step: float = STEP,
) -> NDArray[np.float32]:
    """Pit-free CHM on ``window`` from points at ``xy`` with ``height`` above ground.

    Pass vegetation points and ground points (height 0). Cells no layer covers
    take the highest point in the cell, or 0 where the cell is empty.
    """
    xy = np.asarray(xy, np.float64)
    h = np.maximum(np.asarray(height, np.float64), 0.0)
    out = np.full(window.rows * window.cols, -np.inf)
    gx, gy = window.centers()
    q = np.column_stack([gx.ravel(), gy.ravel()])
    if xy.shape[0] == 0:
        return np.zeros((window.rows, window.cols), np.float32)
    origin = xy.mean(axis=0)
    # Points within a margin of the window: a layer needs the triangles around the border.
    lo = np.array([window.xmin, window.ymax - window.rows * window.resolution]) - max_edge
    hi = np.array([window.xmin + window.cols * window.resolution, window.ymax]) + max_edge
    near = np.all((xy >= lo) & (xy <= hi), axis=1)
    xy, h = xy[near] - origin, h[near]
    q = q - origin
    ladder = np.arange(0.0, float(h.max(initial=0.0)) + step, step)
    for t in ladder:
        sel = h >= t
        if t > 0 and not sel.any():
            break
        if np.count_nonzero(sel) < 3:
            continue
        _layer(xy[sel], h[sel], q, max_edge if t > 0 else np.inf, out)
    # Highest point per cell where no triangle reached (isolated points).
    row, col, inside = window.cell_of(xy[:, 0] + origin[0], xy[:, 1] + origin[1])
    flat = row[inside] * window.cols + col[inside]
    top = np.full(out.size, -np.inf)
    np.maximum.at(top, flat, h[inside])
    out = np.where(np.isfinite(out), out, top)
    out[~np.isfinite(out)] = 0.0
    return out.reshape(window.rows, window.cols).astype(np.float32)


def _with_transform(tri: Delaunay) -> Delaunay:
    """Give a 2-D ``tri`` its barycentric transforms, computed here in numpy.

    scipy builds ``Delaunay.transform`` (needed by ``find_simplex``) with one
    LAPACK call per simplex; under a multi-threaded OpenBLAS on a busy machine
    that costs up to 100x more than this closed-form 2x2 inverse. Degenerate
    (zero-area) simplices get NaN, as scipy gives them.
    """
    if getattr(tri, "_transform", 0) is not None or tri.ndim != 2:
        return tri
    pts = tri.points[tri.simplices]
    r = pts[:, 2]
    a = pts[:, 0] - r
    b = pts[:, 1] - r
    det = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
    scale = np.maximum(np.abs(a).sum(axis=1) * np.abs(b).sum(axis=1), np.finfo(float).tiny)
    det = np.where(np.abs(det) > 1e3 * np.finfo(float).eps * scale, det, np.nan)
    t = np.empty((det.size, 3, 2))
    t[:, 0, 0] = b[:, 1] / det
    t[:, 0, 1] = -b[:, 0] / det
    t[:, 1, 0] = -a[:, 1] / det
    t[:, 1, 1] = a[:, 0] / det
    t[:, 2] = r
    tri._transform = t
    return tri


_QHULL_OPTIONS = "Qbb Qc Qz Q12 Q3 Q5 Q8"
"""scipy's 2-D defaults (Qbb Qc Qz Q12) plus Qhull's speed options: no merge of
redundant vertices, no outer-plane check, near-inside points ignored (~7 % on
LiDAR ground, ~25 % on scattered points; the same triangles)."""


def _triangulate(xy: NDArray[np.float64]) -> tuple[Delaunay, NDArray[np.int64]]:
    """Delaunay triangulation of ``xy``, with transforms for ``find_simplex``,
    and its simplices numbered as the rows of ``xy``.

    Qhull is fed the points in serpentine order of cells holding ~64 points
    each: on cloud order (sorted by x, or scan lines) it spends ~30 % longer
    on the same triangles. ``find_simplex`` answers simplex indices, which
    do not depend on the vertex numbering. Raises QhullError as Delaunay does.
    """
    xy = np.asarray(xy, dtype=np.float64)
    order = np.arange(xy.shape[0])
    if xy.shape[0] > 64:
        span = np.ptp(xy, axis=0)
        cell = float(np.sqrt(64.0 * span[0] * span[1] / xy.shape[0]))
        if cell > 1e-3 * span.max():  # not (nearly) collinear
            order = spatial_order(xy, cell)
    tri = _with_transform(Delaunay(xy[order], qhull_options=_QHULL_OPTIONS))
    return tri, order[tri.simplices]


def _layer(
    xy: NDArray[np.float64],
    h: NDArray[np.float64],
    q: NDArray[np.float64],
    max_edge: float,
    out: NDArray,
) -> None:
    """Raise ``out`` to this layer's TIN at the query points its short-edged triangles cover."""
    try:
        tri, simplices = _triangulate(xy)
    except (QhullError, ValueError):
        return
    s = tri.find_simplex(q)
    hit = s >= 0
    if not hit.any():
        return
    verts = simplices[s[hit]]
    p = xy[verts]
    edge = np.max(
        np.stack(
            [
                np.hypot(*(p[:, 0] - p[:, 1]).T),
                np.hypot(*(p[:, 1] - p[:, 2]).T),
                np.hypot(*(p[:, 2] - p[:, 0]).T),
            ]
        ),
        axis=0,
    )
    keep = edge <= max_edge
    idx = np.flatnonzero(hit)[keep]
    if idx.size == 0:
        return
    tr = tri.transform[s[idx]]
    b = np.einsum("nij,nj->ni", tr[:, :2], q[idx] - tr[:, 2])
    bary = np.column_stack([b, 1.0 - b.sum(axis=1)])
    # ``simplices`` keep Qhull's vertex order, which the barycentric weights follow.
    z = np.einsum("ni,ni->n", bary, h[simplices[s[idx]]])
    out[idx] = np.maximum(out[idx], z)
