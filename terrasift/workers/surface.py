"""Delaunay TINs through points: ``triangulate`` (Qhull, with the simplices and
point location a ground filter needs) and ``TinSurface`` (a ground surface:
linear on a TIN, nearest vertex outside it).

Point location is a walk from the last hit, fed queries in a serpentine spatial
order, so each walk is a step or two. Qhull's barycentric transforms come from
``with_transform``: scipy builds them with one LAPACK call per simplex, which
under a threaded BLAS on a busy machine took over 100 s for a 150 k point TIN.

Coordinates are shifted to a local origin before triangulating, because
projected coordinates (5e6 m) cost precision.
"""

from __future__ import annotations

import numpy as np
import startinpy
from numpy.typing import NDArray
from scipy.spatial import Delaunay, cKDTree


def with_transform(tri: Delaunay) -> Delaunay:
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


def spatial_order(xy: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Serpentine row order of ``cell``-sized bins: consecutive points are close,
    which is what makes ``Delaunay.find_simplex`` (a walk from its last hit) fast."""
    ix = np.floor((xy[:, 0] - xy[:, 0].min()) / cell).astype(np.int64)
    iy = np.floor((xy[:, 1] - xy[:, 1].min()) / cell).astype(np.int64)
    nx = int(ix.max()) + 1
    ix = np.where(iy % 2 == 1, nx - 1 - ix, ix)
    return np.argsort(iy * nx + ix)


QHULL_OPTIONS = "Qbb Qc Qz Q12 Q3 Q5 Q8"
"""scipy's 2-D defaults (Qbb Qc Qz Q12) plus Qhull's speed options: no merge of
redundant vertices, no outer-plane check, near-inside points ignored (~7 % on
LiDAR ground, ~25 % on scattered points; the same triangles)."""


def triangulate(xy: NDArray[np.float64]) -> tuple[Delaunay, NDArray[np.int64]]:
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
    tri = with_transform(Delaunay(xy[order], qhull_options=QHULL_OPTIONS))
    return tri, order[tri.simplices]


class TinSurface:
    """z(x, y) linearly interpolated on the TIN of ``xyz``; nearest vertex outside the hull.

    Built with startin's incremental Delaunay (vertices fed in serpentine cell
    order, so each insertion walks a step or two) and sampled with its TIN
    interpolation: on a block's 1 m ground vertices this is ~2x faster than a
    Qhull triangulation plus ``find_simplex``, for the same triangles and the
    same heights. Points closer than 1 mm in x, y keep the lowest.
    """

    def __init__(self, xyz: NDArray[np.float64]):
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.shape[0] == 0:
            raise ValueError("a surface needs at least one point")
        self.origin = xyz[:, :2].mean(axis=0)
        self.xy = xyz[:, :2] - self.origin
        self.z = xyz[:, 2].copy()
        self._dt: startinpy.DT | None = None
        if xyz.shape[0] >= 3:
            local = np.column_stack([self.xy, self.z])
            cell = float(
                np.sqrt(4.0 * max(float(np.prod(np.ptp(self.xy, axis=0))), 1e-6) / xyz.shape[0])
            )
            dt = startinpy.DT()
            dt.duplicates_handling = "Lowest"
            dt.insert(local[spatial_order(self.xy, max(cell, 1e-3))], insertionstrategy="AsIs")
            self._dt = dt
        self._kd: cKDTree | None = None

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        q = np.column_stack([np.ravel(x), np.ravel(y)]) - self.origin
        out = np.full(q.shape[0], np.nan)
        if self._dt is not None and q.shape[0]:
            # Queries in a spatial order: each walk starts from the last hit.
            order = spatial_order(q, 8.0)
            out[order] = self._dt.interpolate({"method": "TIN"}, q[order])
        outside = np.isnan(out)
        if outside.any():
            if self._kd is None:
                self._kd = cKDTree(self.xy)
            _, nearest = self._kd.query(q[outside])
            out[outside] = self.z[nearest]
        return out.reshape(np.shape(x))
