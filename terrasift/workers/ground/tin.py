"""Fast TIN tools for the NIST ground filter: point location, interpolation, screening.

``scipy.spatial.Delaunay.find_simplex`` costs a few microseconds per query
point, which is the whole throughput budget of the ground stage. ``Tin``
locates points instead with a directed walk, compiled with numba: a coarse
raster of triangle ids gives every query a starting triangle within about
one triangle of it, and the walk steps across the edge facing the query
until it is inside. Walks on a Delaunay triangulation terminate; callers
pass points in cell order, so consecutive queries touch the same triangles.

Triangulations come from startinpy's incremental insertion (``delaunay``),
several times faster than Qhull on the hundreds of thousands of vertices of a
final TIN; Qhull remains the fallback for degenerate input. Coordinates are
shifted to a local origin before triangulating (precision on projected
coordinates of 5e6 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import startinpy
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError

from terrasift.workers.ground import _kernels
from terrasift.workers.ground._kernels import (
    _EXTRAPOLATE,
    _LOCATE,
    _NEAREST,
    _adjacency,
    _band_kernel,
    _edge_neighbours,
    _judge_kernel,
    _near_outline,
    _surface_kernel,
    _walk_kernel,
)

IN_BAND, ABOVE, BELOW = _kernels.IN_BAND, _kernels.ABOVE, _kernels.BELOW  # codes of Tin.band
_GUESS_K = 0.5
_SNAP = 1e-9  # startinpy merges points closer than this (local metres); Qhull takes those
REBUILD_SHARE = 0.3  # Tin.without rebuilds the whole TIN when the holes' rims hold more


def delaunay(
    xy: NDArray[np.float64],
    *,
    coincident: bool = False,
    order: NDArray[np.int64] | None = None,
) -> Mesh | Delaunay:
    """Delaunay triangulation of the 2-D points ``xy``, as a ``Mesh`` or a scipy ``Delaunay``.

    startinpy (incremental insertion, robust predicates) builds it 3-4 times
    faster than Qhull; the triangles are the same wherever the triangulation is
    unique (no four co-circular points). Of points at the same position only
    the first is a vertex (Qhull keeps an arbitrary one); the others are in no
    triangle. Points closer than ``_SNAP`` but not equal, collinear input, or a
    result that does not check out as a triangulation are left to Qhull, which
    raises QhullError on collinear points as before. ``coincident``: the caller
    expects coincident points, so they are sorted out before triangulating
    rather than after a first attempt. ``order``: insert the points in this
    order, one after the other, which decides the triangles where four or more
    points are co-circular (the default picks an order for speed).
    """
    n = xy.shape[0]
    if n >= 3:
        s = None if coincident else _startin(xy, order)
        if s is not None:
            mesh = Mesh.from_simplices(s, n, n)
        else:
            o = np.lexsort((xy[:, 1], xy[:, 0]))  # stable: a position's first index leads its run
            lead = np.ones(n, dtype=bool)
            lead[1:] = (xy[o[1:]] != xy[o[:-1]]).any(axis=1)
            keep = np.sort(o[lead])
            s = _startin(xy[keep]) if keep.size >= 3 else None
            mesh = (
                None if s is None else Mesh.from_simplices(keep.astype(np.int32)[s], n, keep.size)
            )
        if mesh is not None:
            return mesh
    return Delaunay(xy)


def _startin(
    xy: NDArray[np.float64], given: NDArray[np.int64] | None = None
) -> NDArray[np.int32] | None:
    """startinpy's triangles (counter-clockwise, 0-based) over ``xy``, or None
    when it merged points or found no triangle. ``given``: the insertion order."""
    n = xy.shape[0]
    order = _insertion_order(xy) if given is None else given.astype(np.int32)
    dt = startinpy.DT()
    dt.snap_tolerance = _SNAP
    dt.insert(
        np.column_stack([xy if order is None else xy[order], np.zeros(n)]),
        insertionstrategy="BBox" if given is None else "AsIs",
    )
    if dt.number_of_vertices() != n:
        return None
    s = np.asarray(dt.triangles)
    if s.shape[0] == 0:
        return None
    s = s.astype(np.int32)
    s -= 1  # vertex 0 is startinpy's infinite vertex
    return s if order is None else order[s]


def _insertion_order(xy: NDArray[np.float64]) -> NDArray[np.int32] | None:
    """Hilbert order for scattered points, None for points already in a
    spatially coherent order (consecutive points a few spacings apart on
    average, as in grid or cell order).

    startinpy's walk to each new point starts at the previous one: in file
    order a point pool of 150 k triangulates 9 times slower than sorted, while
    on coherent input the sort costs more than it saves.
    """
    n = xy.shape[0]
    if n < 64:
        return None
    x, y = xy[:, 0], xy[:, 1]
    jump = float(np.abs(np.diff(x)).mean() + np.abs(np.diff(y)).mean())
    area = float((x.max() - x.min()) * (y.max() - y.min()))
    if jump < 8.0 * np.sqrt(area / n):
        return None
    return np.argsort(hilbert_key(xy), kind="stable").astype(np.int32)


def hilbert_key(xy: NDArray[np.float64]) -> NDArray[np.int64]:
    """Position of each point of ``xy`` along a Hilbert curve over its bounding
    square, on a grid of about one point per cell: sorting by it keeps
    neighbours in the plane near each other in the sequence."""
    n = xy.shape[0]
    bits = int(min(16, max(1, np.ceil(np.log2(max(n, 2)) / 2))))
    side = 1 << bits
    lo = np.array([xy[:, 0].min(), xy[:, 1].min()])
    span = max(float(max(xy[:, 0].max() - lo[0], xy[:, 1].max() - lo[1])), 1e-300)
    x = np.clip(((xy[:, 0] - lo[0]) * (side / span)).astype(np.int64), 0, side - 1)
    y = np.clip(((xy[:, 1] - lo[1]) * (side / span)).astype(np.int64), 0, side - 1)
    d = np.zeros(n, dtype=np.int64)
    s = side >> 1
    while s:  # one pass per bit, from the top quadrant down
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx) ^ ry)
        flip = ~ry  # rotate the quadrant so the curve enters and leaves it right
        back = flip & rx
        x = np.where(back, side - 1 - x, x)
        y = np.where(back, side - 1 - y, y)
        x, y = np.where(flip, y, x), np.where(flip, x, y)
        s >>= 1
    return d


@dataclass(frozen=True)
class FacetPlanes:
    """Per facet: unit normal, |n_z| (the cosine of its slope), offset n · corner, horizontal area."""

    unit: NDArray[np.float64]
    nz: NDArray[np.float64]
    offset: NDArray[np.float64]
    area: NDArray[np.float64]


class Tin:
    """Delaunay TIN through ``xyz``, linear inside the hull, nearest corner outside it."""

    def __init__(
        self,
        xyz: NDArray[np.float64],
        origin: NDArray[np.float64] | None = None,
        *,
        coincident: bool = False,
        order: NDArray[np.int64] | None = None,
    ):
        """``coincident``: points may share a position; ``order``: of insertion (see ``delaunay``)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.shape[0] < 3:
            raise ValueError("a TIN needs at least three points")
        self.origin = (
            xyz[:, :2].mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
        )
        self.xy = xyz[:, :2] - self.origin
        self.z = xyz[:, 2].copy()
        # QhullError (collinear input) propagates to the caller
        self.tri = delaunay(self.xy, coincident=coincident, order=order)
        self._slopes: NDArray[np.float64] | None = None
        self._trans: NDArray[np.float64] | None = None
        self._guess: tuple[float, float, float, int, int, NDArray[np.int64]] | None = None
        self._zt: NDArray[np.float64] | None = None
        self._planes: FacetPlanes | None = None

    @classmethod
    def _from_mesh(
        cls,
        xy: NDArray[np.float64],
        z: NDArray[np.float64],
        origin: NDArray[np.float64],
        mesh: Mesh,
    ) -> Tin:
        tin = cls.__new__(cls)
        tin.origin, tin.xy, tin.z, tin.tri = origin, xy, z, mesh
        tin._slopes = tin._trans = tin._guess = tin._zt = tin._planes = None
        return tin

    @property
    def n_vertices(self) -> int:
        return self.xy.shape[0]

    def without(self, drop: NDArray[np.bool_]) -> Tin:
        """The Delaunay TIN of the vertices not in ``drop`` (same origin, vertices in order).

        Only the holes left by the dropped vertices are re-triangulated: the
        triangles of the new TIN inside a hole have the hole's rim vertices as
        corners and are Delaunay among them, so one Qhull call over all rims
        gives them (those whose centroid falls in a hole), while every other
        triangle stays. A few thousand screened vertices thus cost a small
        triangulation instead of a full one. Falls back to a full rebuild when
        the rims are most of the TIN or the merge does not check out as a
        triangulation (near-cocircular rims solved another way by Qhull).
        Raises ValueError / QhullError as the constructor does.
        """
        keepv = ~drop
        nk = int(np.count_nonzero(keepv))
        if nk == self.n_vertices:
            return self
        if nk < 3:
            raise ValueError("a TIN needs at least three points")
        s = np.asarray(self.tri.simplices)
        hole = drop[s].any(axis=1)
        rim_s = s[hole]
        rim = np.unique(rim_s[keepv[rim_s]])
        if rim.size < 3 or rim.size > REBUILD_SHARE * nk:
            return self._rebuilt(keepv)
        try:
            sub = delaunay(self.xy[rim])
        except QhullError:
            return self._rebuilt(keepv)
        ss = rim[sub.simplices]
        # Centroids walk from a hole triangle at one of their corners: a step or two.
        hole_ids = np.flatnonzero(hole)
        start = np.zeros(self.n_vertices, dtype=np.int64)
        start[rim_s.ravel()] = np.repeat(hole_ids, 3)
        t = self._walk(self.xy[ss].mean(axis=1), start[ss[:, 0]], self._transform())[0]
        fill = ss[(t >= 0) & hole[np.maximum(t, 0)]]
        mesh = Mesh.patched(s, np.asarray(self.tri.neighbors), hole, fill, keepv)
        if mesh is None:
            return self._rebuilt(keepv)
        if not drop[np.unique(self.tri.convex_hull)].any():
            # Same hull: the fill must cover the holes' area exactly.
            a_hole, a_fill = _area(self.xy, s[hole]).sum(), _area(self.xy, fill).sum()
            if abs(a_fill - a_hole) > 1e-9 * max(a_hole, 1.0):
                return self._rebuilt(keepv)
        tin = Tin._from_mesh(self.xy[keepv], self.z[keepv], self.origin, mesh)
        # The kept triangles come first, corners in order: their transforms carry over.
        tin._trans = np.concatenate([self._transform()[~hole], _transforms(self.xy, fill)])
        return tin

    def _rebuilt(self, keepv: NDArray[np.bool_]) -> Tin:
        """A fresh TIN of the vertices in ``keepv`` (the fallback of ``without``)."""
        return Tin(
            np.column_stack([self.xy[keepv] + self.origin, self.z[keepv]]), origin=self.origin
        )

    def neighbours(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """CSR adjacency (indptr, indices) of TIN vertices."""
        indptr, indices = self.tri.vertex_neighbor_vertices
        return indptr.astype(np.int64), indices.astype(np.int64)

    def _start_raster(self) -> tuple[float, float, float, int, int, NDArray[np.int64]]:
        """A coarse raster of triangle ids over the TIN (each cell: the triangle
        whose centroid falls in it, or the nearest such), built once: a query's
        walk starts from its cell's triangle, about one triangle away."""
        if self._guess is None:
            simp = self.tri.simplices
            x, y = self.xy[:, 0], self.xy[:, 1]
            s0, s1, s2 = simp[:, 0], simp[:, 1], simp[:, 2]
            cen = np.column_stack([(x[s0] + x[s1] + x[s2]) / 3.0, (y[s0] + y[s1] + y[s2]) / 3.0])
            lo = self.xy.min(axis=0)
            hi = self.xy.max(axis=0)
            area = max(float(np.prod(hi - lo)), 1e-12)
            h = max(np.sqrt(_GUESS_K * area / simp.shape[0]), 1e-6)
            nx = int((hi[0] - lo[0]) / h) + 1
            ny = int((hi[1] - lo[1]) / h) + 1
            ix = np.clip(((cen[:, 0] - lo[0]) / h).astype(np.int64), 0, nx - 1)
            iy = np.clip(((cen[:, 1] - lo[1]) / h).astype(np.int64), 0, ny - 1)
            raster = np.full((ny, nx), -1, dtype=np.int64)
            raster[iy, ix] = np.arange(simp.shape[0])
            empty = raster < 0
            if empty.any():
                idx = ndimage.distance_transform_edt(
                    empty, return_distances=False, return_indices=True
                )
                raster = raster[idx[0], idx[1]]
            self._guess = (float(lo[0]), float(lo[1]), h, nx, ny, raster.ravel())
        return self._guess

    def _nbr(self) -> NDArray:
        """Neighbour triangle opposite each corner, flat (3 per triangle, -1 on the hull)."""
        return np.ravel(self.tri.neighbors)

    def _transform(self) -> NDArray[np.float64]:
        if self._trans is None:
            self._trans = _transforms(self.xy, self.tri.simplices)
        return self._trans

    def locate(self, q: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Triangle and barycentric coordinates of local points ``q``.

        Points outside the hull get the hull triangle where their walk left
        the mesh and a triangle index of -(t + 1).
        """
        t, b0, b1 = self._located(q, _LOCATE)
        return t, np.column_stack([b0, b1, 1.0 - b0 - b1])

    def _walk(
        self, q: NDArray[np.float64], t: NDArray[np.int64], trans: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Directed walk of every query ``q`` from its start triangle ``t``: the
        triangles (as ``locate``) and the first two barycentric coordinates."""
        q = np.ascontiguousarray(q, dtype=np.float64)
        t = np.array(t, dtype=np.int64)
        b0 = np.empty(q.shape[0])
        b1 = np.empty(q.shape[0])
        _walk_kernel(q, t, trans, self._nbr(), b0, b1)
        return t, b0, b1

    def _mesh_args(self) -> tuple:
        """The arrays every compiled location pass reads."""
        x0, y0, h, nx, ny, raster = self._start_raster()
        return x0, y0, h, nx, ny, raster, self._transform(), self._nbr()

    def _located(
        self, q: NDArray[np.float64], mode: int, want_slope: bool = False
    ) -> tuple[NDArray, ...]:
        """One compiled pass over the local points ``q`` (see ``_surface_kernel``):
        triangles and the first two barycentric coordinates (``_LOCATE``), or
        triangles, heights and facet slopes (if ``want_slope``)."""
        n = q.shape[0]
        locate = mode == _LOCATE
        t = np.empty(n if mode != _NEAREST else 0, dtype=np.int64)
        b0 = np.empty(n if locate else 0)
        b1 = np.empty(n if locate else 0)
        z = np.empty(0 if locate else n)
        slopes = self.facet_slopes() if want_slope else np.empty(0)
        sl = np.empty(n if want_slope else 0)
        zt = np.empty((0, 3)) if locate else self._corner_z()
        _surface_kernel(
            np.asarray(q, dtype=np.float64), 0.0, 0.0, *self._mesh_args(),
            zt, self.xy, self.tri.simplices, slopes, mode, t, b0, b1, z, sl,
        )  # fmt: skip
        if locate:
            return t, b0, b1
        return t, z, sl

    def band(
        self,
        xyz: NDArray[np.float64],
        up: float,
        down: float,
        gain: float = 0.0,
        cap: float = np.inf,
    ) -> NDArray[np.int8]:
        """Where each point of ``xyz`` (absolute coordinates) lies against the surface:
        ``ABOVE`` more than ``up`` over it, ``IN_BAND`` down to ``down`` under it,
        else ``BELOW``; both tolerances grow by ``gain`` × facet slope (capped at
        ``cap``) when ``gain`` > 0. Heights as ``height_and_slope``; one compiled
        pass, no per-point arrays but the codes."""
        xyz = np.asarray(xyz, dtype=np.float64)
        code = np.empty(xyz.shape[0], dtype=np.int8)
        slopes = self.facet_slopes() if gain > 0 else np.empty(0)
        _band_kernel(
            xyz, float(self.origin[0]), float(self.origin[1]), *self._mesh_args(),
            self._corner_z(), self.xy, self.tri.simplices, slopes, up, down, gain, cap, code,
        )  # fmt: skip
        return code

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Surface height at absolute ``x, y``."""
        q = np.column_stack([np.ravel(x) - self.origin[0], np.ravel(y) - self.origin[1]])
        return self.at_local(q).reshape(np.shape(x))

    def at_local(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """Surface height at local points ``q`` (n, 2)."""
        return self.height_and_slope(q, slope=False)[0]

    def height_and_slope(
        self, q: NDArray[np.float64], slope: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Surface height (the nearest corner of the exit triangle outside the
        hull) and facet slope (rise over run) at local points ``q``, one walk for both."""
        _, h, sl = self._located(q, _NEAREST, slope)
        return h, sl if slope else None

    def linear(self, q: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Triangle (the exit triangle outside the hull) and height of its plane at
        local points ``q``: linear extrapolation beyond the hull."""
        t, h, _ = self._located(q, _EXTRAPOLATE)
        return t, h

    def _corner_z(self) -> NDArray[np.float64]:
        # Heights of the three corners of every triangle: one gather per query
        # instead of corner ids, then heights.
        if self._zt is None:
            self._zt = self.z[self.tri.simplices]
        return self._zt

    @cached_property
    def simplices(self) -> NDArray[np.int64]:
        """Corner vertices of every facet."""
        return np.asarray(self.tri.simplices, dtype=np.int64)

    @cached_property
    def local_xyz(self) -> NDArray[np.float64]:
        """The vertices in local coordinates (x, y less ``origin``; z as given)."""
        return np.column_stack([self.xy, self.z])

    def facet_of(self, q: NDArray[np.float64]) -> NDArray[np.int64]:
        """Facet under each local point of ``q``, -1 outside the hull; fastest when
        consecutive points are close."""
        t, _ = self.locate(np.asarray(q, dtype=np.float64))
        return np.where(t >= 0, t, -1)

    def facet_planes(self) -> FacetPlanes:
        """The plane of every facet (cached): for distances of points to facets."""
        if self._planes is None:
            p = self.local_xyz[self.simplices]
            normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            norm = np.linalg.norm(normal, axis=1)
            norm[norm == 0] = np.inf
            unit = normal / norm[:, None]
            self._planes = FacetPlanes(
                unit=unit,
                nz=np.abs(unit[:, 2]),
                offset=np.einsum("ij,ij->i", unit, p[:, 0]),
                area=0.5 * np.abs(normal[:, 2]),
            )
        return self._planes

    def plane_distance(self, s: NDArray[np.int64], pts: NDArray[np.float64]) -> NDArray[np.float64]:
        """Perpendicular distance of each local point to the plane of its facet ``s``."""
        planes = self.facet_planes()
        return np.abs(np.einsum("ij,ij->i", pts, planes.unit[s]) - planes.offset[s])

    def nearest_corner(
        self, s: NDArray[np.int64], pts: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distance to the nearest corner of facet ``s`` and that corner, per local point."""
        vs = self.local_xyz[self.simplices[s]]  # (m, 3, 3)
        d2 = ((vs - pts[:, None, :]) ** 2).sum(axis=2)
        k = np.argmin(d2, axis=1)
        r = np.arange(s.size)
        return np.sqrt(d2[r, k]), vs[r, k]

    def facet_slopes(self) -> NDArray[np.float64]:
        """Gradient magnitude of each triangle."""
        if self._slopes is not None:
            return self._slopes
        s = self.tri.simplices
        p = self.xy[s]
        dz1 = self.z[s[:, 1]] - self.z[s[:, 0]]
        dz2 = self.z[s[:, 2]] - self.z[s[:, 0]]
        a = p[:, 1] - p[:, 0]
        b = p[:, 2] - p[:, 0]
        det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            gx = (dz1 * b[:, 1] - dz2 * a[:, 1]) / det
            gy = (dz2 * a[:, 0] - dz1 * b[:, 0]) / det
        self._slopes = np.nan_to_num(np.hypot(gx, gy), nan=0.0, posinf=0.0)
        return self._slopes


def _transforms(xy: NDArray[np.float64], s: NDArray) -> NDArray[np.float64]:
    """Barycentric transform of each triangle ``s`` (rows of six numbers), vectorised:
    scipy's ``Delaunay.transform`` loops in Python-speed LAPACK calls."""
    p0, p1, p2 = xy[s[:, 0]], xy[s[:, 1]], xy[s[:, 2]]
    a, b = p0 - p2, p1 - p2
    det = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
    inv[~np.isfinite(inv)] = np.nan
    return np.column_stack([b[:, 1] * inv, -b[:, 0] * inv, -a[:, 1] * inv, a[:, 0] * inv, p2])


def _area(xy: NDArray[np.float64], s: NDArray[np.int64]) -> NDArray[np.float64]:
    """Unsigned area of the triangles ``s``."""
    a = xy[s[:, 1]] - xy[s[:, 0]]
    b = xy[s[:, 2]] - xy[s[:, 0]]
    return 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


class Mesh:
    """Triangles of a TIN with the topology ``Tin`` reads from a scipy ``Delaunay``:
    ``simplices``, ``neighbors`` (opposite each corner, -1 on the hull),
    ``vertex_neighbor_vertices`` and ``convex_hull`` (edges)."""

    def __init__(self, simplices: NDArray, neighbors: NDArray, n: int):
        self.simplices = simplices
        self.neighbors = neighbors
        self._n = n
        self._vnv: tuple[NDArray, NDArray] | None = None

    @classmethod
    def from_simplices(cls, simplices: NDArray[np.int32], n: int, used: int) -> Mesh | None:
        """The mesh of counter-clockwise triangles ``simplices`` over ``n`` vertices,
        or None unless it is a triangulated disc using ``used`` of them.

        The triangle across edge (a, b) is the one holding the reversed edge
        (b, a), found among the few edges leaving b (``_edge_neighbours``).
        """
        m = simplices.shape[0]
        nb, hull, vertices = _edge_neighbours(np.ascontiguousarray(simplices), n)
        if hull < 0 or m != 2 * used - 2 - hull or vertices != used:
            return None  # hull < 0: a directed edge twice (overlap or mixed orientation)
        return cls(simplices, nb, n)

    @classmethod
    def patched(
        cls,
        simplices: NDArray,
        neighbors: NDArray,
        hole: NDArray[np.bool_],
        fill: NDArray,
        keepv: NDArray[np.bool_],
    ) -> Mesh | None:
        """The mesh with the ``hole`` triangles replaced by ``fill`` (old vertex ids)
        and vertices renumbered to those in ``keepv``, or None unless the result is
        a triangulated disc using every kept vertex (each edge in one or two
        triangles, Euler's count).

        Only the edges around the holes are matched (one sort over them); the
        other triangles keep their neighbours, renumbered.
        """
        kt = np.flatnonzero(~hole)
        mk, f = kt.size, fill.shape[0]
        # One extra entry at the end answers the hull's -1 neighbours in one gather.
        tid = np.full(simplices.shape[0] + 1, -1, dtype=np.int32)
        tid[kt] = np.arange(mk)
        nb_old = neighbors[kt]
        border = np.append(hole, False)[nb_old]
        nb = np.concatenate([tid[nb_old].ravel(), np.full(3 * f, -1, dtype=np.int32)])
        bk, bj = np.nonzero(border)
        sk = simplices[kt[bk]]
        ea = np.concatenate([sk[np.arange(bk.size), (bj + 1) % 3], fill[:, [1, 2, 0]].ravel()])
        eb = np.concatenate([sk[np.arange(bk.size), (bj + 2) % 3], fill[:, [2, 0, 1]].ravel()])
        slot = np.concatenate([3 * bk + bj, 3 * mk + np.arange(3 * f)])
        n_old = keepv.size
        key = np.minimum(ea, eb).astype(np.int64) * n_old + np.maximum(ea, eb)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        same = ks[1:] == ks[:-1]
        if (same[1:] & same[:-1]).any():
            return None  # an edge in three triangles: overlap
        i, j = slot[order[:-1][same]], slot[order[1:][same]]
        if ((i < 3 * mk) & (j < 3 * mk)).any():
            return None
        nb[i] = j // 3
        nb[j] = i // 3
        new_id = np.cumsum(keepv, dtype=np.int32) - 1
        merged = new_id[np.concatenate([simplices[kt], fill])]
        n, m = int(new_id[-1]) + 1, mk + f
        if m != 2 * n - 2 - int(np.count_nonzero(nb < 0)):
            return None
        if np.count_nonzero(np.bincount(merged.ravel(), minlength=n)) != n:
            return None
        return cls(merged, nb.reshape(m, 3), n)

    @property
    def convex_hull(self) -> NDArray[np.int32]:
        t, j = np.nonzero(self.neighbors < 0)
        s = self.simplices
        return np.column_stack([s[t, (j + 1) % 3], s[t, (j + 2) % 3]])

    @property
    def vertex_neighbor_vertices(self) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        if self._vnv is None:
            self._vnv = _adjacency(np.asarray(self.simplices), np.asarray(self.neighbors), self._n)
        return self._vnv


def screen(
    xyz: NDArray[np.float64],
    screen_tol: float,
    low_tol: float,
    *,
    slopes: NDArray[np.float64] | None = None,
    max_rounds: int = 50,
    rim_len: float = 0.0,
    rim_band: float = 0.0,
) -> tuple[NDArray[np.int64], Tin | None]:
    """Points of ``xyz`` kept by TIN screening (NIST §3.2), repeated until stable, and their TIN.

    A vertex is deleted when it stands more than ``screen_tol`` above the
    median of its TIN neighbours. With ``slopes`` (per point: dz/dx, dz/dy of
    the bin plane it came from, §7) each neighbour votes with its height
    extrapolated along its own plane to the vertex, so a vertex on a steep but
    smooth slope or ridge is not mistaken for an object. Without slopes the
    plain median is used and hull vertices are left alone: their neighbours
    all lie on one side, so on any slope the upper hull would be peeled away.

    Isolated low outliers (multipath, common in airborne data) would pull the
    surface into pits, so a vertex is also deleted when it lies more than
    ``low_tol`` below the second-lowest of its neighbours: a pit, not a valley,
    since along a valley floor the neighbours up and down the valley are as
    low as the vertex. Pit votes use only the neighbours' own planes, since
    the plane of the vertex's bin is tilted by the outlier itself.
    ``low_tol <= 0`` skips that test.

    Along the data's edge the TIN joins vertices far apart by slivers: with
    ``rim_len`` > 0 a neighbour does not vote when the edge to it is longer
    than that and both ends lie within ``rim_band`` of the outline (the
    convex hull of ``xyz``). Otherwise a plateau reaching the edge is voted
    down by terrain tens of metres away along the edge, vertex after vertex.

    Rounds after the first only re-triangulate the holes the deletions
    leave (``HoledTin.patch``, as ``Tin.without``) and judge again only the
    vertices around them, the only ones whose neighbours changed.
    """
    n = xyz.shape[0]
    if n < 4:
        return np.arange(n), None
    origin = xyz[:, :2].mean(axis=0)
    try:
        tin = Tin(xyz, origin=origin)
    except QhullError:
        return np.arange(n), None
    hull = np.zeros(n, dtype=bool)
    hull[np.unique(tin.tri.convex_hull)] = True
    rim = np.zeros(n, dtype=bool)
    if rim_len > 0:
        rim = _within_of_hull(tin.xy, tin.tri.convex_hull, rim_band)
    # ids: global id of each vertex of the current TIN; test: its vertices to judge
    done, ids, test, out = _holed_rounds(
        tin, xyz, hull, rim, screen_tol, low_tol, slopes, max_rounds, rim_len
    )
    if test.size == 0 or done == max_rounds:
        return ids, out
    if out is not None:  # handed over at round ``done`` (Tin.without rebuilds): same state
        tin = out
    for _ in range(done, max_rounds):
        ptr, idx = tin.neighbours()
        bad = _judge(tin, ptr, idx, ids, test, xyz, screen_tol, low_tol, slopes, rim[ids], rim_len)
        if slopes is None:
            bad &= ~hull[ids]
        if not bad.any():
            break
        if ids.size - np.count_nonzero(bad) < 4:
            return ids[~bad], None
        owner = np.repeat(np.arange(ids.size), np.diff(ptr))
        near = np.zeros(ids.size, dtype=bool)
        near[idx[bad[owner]]] = True
        try:
            tin = tin.without(bad)
        except QhullError:
            return ids[~bad], None
        keep = ~bad
        ids = ids[keep]
        test = np.flatnonzero(near[keep])
    return ids, tin


def _holed_rounds(
    tin: Tin,
    xyz: NDArray[np.float64],
    hull: NDArray[np.bool_],
    rim: NDArray[np.bool_],
    screen_tol: float,
    low_tol: float,
    slopes: NDArray[np.float64] | None,
    max_rounds: int,
    rim_len: float,
) -> tuple[int, NDArray[np.int64], NDArray[np.int64], Tin | None]:
    """``screen``'s rounds on a ``HoledTin`` (same verdicts, same TIN), until done
    (the rounds made, the ids kept, an empty ``test`` and the TIN or None, as
    ``screen`` returns them) or until a round where ``Tin.without`` would rebuild
    the TIN: then that round, the ids, the (local) vertices to judge and the TIN
    at its start, for ``screen``'s own rounds to go on from."""
    from terrasift.workers.ground.holes import HoledTin

    n = xyz.shape[0]
    none = np.zeros(0, dtype=np.int64)
    holed = HoledTin.of(tin)
    if holed is None:
        return 0, np.arange(n), np.arange(n), None
    sl = np.zeros((0, 2)) if slopes is None else np.ascontiguousarray(slopes, dtype=np.float64)
    on_rim = np.ascontiguousarray(rim)
    test = np.arange(n)
    ptr, idx = tin.neighbours()
    rows = test
    for r in range(max_rounds):
        bad = np.zeros(n, dtype=bool)
        _judge_kernel(
            ptr, idx, test, rows, holed.z, holed.xy, sl, screen_tol, low_tol, on_rim, rim_len**2, bad
        )  # fmt: skip
        if slopes is None:
            bad &= ~hull
        drop = test[bad[test]]
        if drop.size == 0:
            return r, holed.ids(), none, holed.tin()
        if holed.n_alive - drop.size < 4:
            return r, np.flatnonzero(holed.alive & ~bad), none, None
        drop.sort()
        nxt = holed.patch(drop)
        if nxt is None:
            ids = holed.ids()
            return r, ids, np.searchsorted(ids, test), holed.tin()
        test = nxt.astype(np.int64)
        got = holed.rows(test)
        if got is None:
            ids = holed.ids()
            return r + 1, ids, np.searchsorted(ids, test), holed.tin()
        ptr, idx = got
        rows = np.arange(test.size)
    return max_rounds, holed.ids(), none, holed.tin()


def _judge(
    tin: Tin,
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    ids: NDArray[np.int64],
    test: NDArray[np.int64],
    xyz: NDArray[np.float64],
    screen_tol: float,
    low_tol: float,
    slopes: NDArray[np.float64] | None,
    rim: NDArray[np.bool_] | None = None,
    rim_len: float = 0.0,
) -> NDArray[np.bool_]:
    """Screening verdict for every vertex of ``tin`` (only ``test`` can be True).

    Neighbour votes are gathered for the ``test`` vertices only: after the
    first round they are the few around the last deletions.
    """
    bad = np.zeros(ids.size, dtype=bool)
    sl = np.zeros((0, 2)) if slopes is None else np.ascontiguousarray(slopes[ids], dtype=np.float64)
    on_rim = np.zeros(ids.size, dtype=bool) if rim is None else np.ascontiguousarray(rim)
    _judge_kernel(
        indptr, indices, test, test, tin.z, tin.xy, sl, screen_tol, low_tol, on_rim, rim_len**2, bad
    )
    return bad


def _within_of_hull(
    xy: NDArray[np.float64], hull_edges: NDArray[np.int32], band: float
) -> NDArray[np.bool_]:
    """Which of ``xy`` lie within ``band`` of the convex hull's outline (its
    edges ``hull_edges``, pairs of indices into ``xy``)."""
    a, b = xy[hull_edges[:, 0]], xy[hull_edges[:, 1]]
    d = b - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    # Distance to each edge's line; inside a convex hull the nearest line is the nearest edge.
    return _near_outline(np.ascontiguousarray(xy), a, d, length, band)
