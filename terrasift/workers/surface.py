"""A ground surface through points: linear on a Delaunay TIN, nearest outside it.

Coordinates are shifted to a local origin before triangulating, because
projected coordinates (5e6 m) cost Qhull precision.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError, cKDTree


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


class TinSurface:
    """z(x, y) linearly interpolated on the TIN of ``xyz``; nearest vertex outside the hull."""

    def __init__(self, xyz: NDArray[np.float64]):
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.shape[0] == 0:
            raise ValueError("a surface needs at least one point")
        self.origin = xyz[:, :2].mean(axis=0)
        self.xy = xyz[:, :2] - self.origin
        self.z = xyz[:, 2].copy()
        self.tri: Delaunay | None = None
        if xyz.shape[0] >= 3:
            try:
                self.tri = with_transform(Delaunay(self.xy))
            except QhullError:  # all points collinear or coincident
                self.tri = None
        self._kd: cKDTree | None = None

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        q = np.column_stack([np.ravel(x), np.ravel(y)]) - self.origin
        out = np.empty(q.shape[0])
        inside = np.zeros(q.shape[0], dtype=bool)
        if self.tri is not None:
            simplex = self.tri.find_simplex(q)
            inside = simplex >= 0
            s = simplex[inside]
            trans = self.tri.transform[s]
            bary2 = np.einsum("nij,nj->ni", trans[:, :2], q[inside] - trans[:, 2])
            bary = np.column_stack([bary2, 1 - bary2.sum(axis=1)])
            out[inside] = np.einsum("ni,ni->n", bary, self.z[self.tri.simplices[s]])
        if not inside.all():
            if self._kd is None:
                self._kd = cKDTree(self.xy)
            _, nearest = self._kd.query(q[~inside])
            out[~inside] = self.z[nearest]
        return out.reshape(np.shape(x))
