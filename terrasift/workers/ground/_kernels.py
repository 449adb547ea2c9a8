"""Compiled kernels of the ground TIN (``tin``) and the supported-points passes
(``support``), of TIN masking (``masking``), kept apart from the numpy code that calls them so an edit there
does not make numba compile them again (its cache follows the source file).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import types
from numba.extending import intrinsic
from numpy.typing import NDArray

_MAX_WALK = 128
_MIX = np.array([0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xD6E8FEB86659FD93], dtype=np.uint64)
_U31 = np.uint64(31)
_U11 = np.uint64(11)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_LOCATE, _NEAREST, _EXTRAPOLATE = 0, 1, 2  # modes of _surface_kernel
IN_BAND, ABOVE, BELOW = 0, 1, 2  # codes of Tin.band
_SORT_WIDTH = 64  # widest neighbour list sorted by insertion (wider: numpy's sort)


# ------------------------------------------------------------ TIN (tin.py)


@intrinsic
def _bits(typingctx, v):
    """The IEEE bits of the float64 ``v`` as a uint64 (a bit cast: no array, so the
    kernels calling it need no reference counting)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(types.uint64))

    return types.uint64(types.float64), codegen


@numba.njit(cache=True, inline="always")
def _walk_one(
    qx: float, qy: float, tt: int, trans: NDArray[np.float64], nbr: NDArray
) -> tuple[int, float, float]:
    """Walk one query from triangle ``tt`` across the edge facing it until it
    is inside a triangle (returned) or leaves the hull (-(exit triangle + 1)),
    with its first two coordinates in the last triangle.

    The exit edge is the most negative coordinate (the first on ties; edge 0
    for a degenerate sliver, whose coordinates are NaN). After half of
    ``_MAX_WALK`` steps, a walk that still goes on is cycling on round-off near
    an edge: its exit edge becomes a pseudo-random negative one, a hash of
    the query's coordinates and the step, so it depends on the query alone.
    """
    c0 = c1 = np.nan
    for step in range(_MAX_WALK):
        dx = qx - trans[tt, 4]
        dy = qy - trans[tt, 5]
        c0 = trans[tt, 0] * dx + trans[tt, 1] * dy
        c1 = trans[tt, 2] * dx + trans[tt, 3] * dy
        c2 = 1.0 - c0 - c1
        if c0 >= -1e-10 and c1 >= -1e-10 and c2 >= -1e-10:
            return tt, c0, c1
        if step >= _MAX_WALK // 2:
            h = _bits(qx) * _GOLDEN
            h ^= _bits(qy) + np.uint64(step)
            h ^= h >> _U31
            j = 0
            best = np.uint64(0)
            for k, c in enumerate((c0, c1, c2)):
                if c < -1e-10 or np.isnan(c):
                    v = (h * _MIX[k]) >> _U11
                    if v > best:
                        best = v
                        j = k
        elif np.isnan(c2) or c0 <= c1 and c0 <= c2:
            j = 0
        elif c1 <= c2:
            j = 1
        else:
            j = 2
        nxt = nbr[3 * tt + j]
        if nxt < 0:
            return -(tt + 1), c0, c1
        tt = nxt
    return -(tt + 1), c0, c1  # still walking (never seen outside degenerate input): outside


@numba.njit(cache=True, inline="always")
def _start(
    qx: float, qy: float, x0: float, y0: float, cell: float, nx: int, ny: int, raster: NDArray
) -> int:
    """The start triangle of a query: its cell of the raster of ``Tin._start_raster``."""
    ix = min(max(int((qx - x0) / cell), 0), nx - 1)
    iy = min(max(int((qy - y0) / cell), 0), ny - 1)
    return raster[iy * nx + ix]


@numba.njit(cache=True, inline="always")
def _height(
    tt: int,
    c0: float,
    c1: float,
    qx: float,
    qy: float,
    zt: NDArray,
    xy: NDArray,
    simplices: NDArray,
    nearest: bool,
) -> float:
    """Height at a located query: the corner heights ``zt`` of its triangle
    interpolated, or outside the hull (``tt`` < 0) with ``nearest`` the height
    of the exit triangle's nearest corner, else its plane's."""
    ti = tt if tt >= 0 else -tt - 1
    if tt < 0 and nearest:
        best = np.inf
        z = np.nan
        for k in range(3):
            v = simplices[ti, k]
            dx = xy[v, 0] - qx
            dy = xy[v, 1] - qy
            d2 = dx * dx + dy * dy
            if d2 < best:
                best = d2
                z = zt[ti, k]
        return z
    # Summed as numpy's einsum sums b · zt: b0·z0, then b2·z2, then b1·z1.
    return c0 * zt[ti, 0] + (1.0 - c0 - c1) * zt[ti, 2] + c1 * zt[ti, 1]


# The per-point kernels below pass arrays to inlined helpers (``_walk_one``,
# ``_start``, ``_height``); with numba's reference counting on, every such call
# counts references of each array, which doubled the cost of a pass over
# millions of points. They allocate nothing, so they are compiled without it.
_NO_RC = {"cache": True, "nogil": True, "_nrt": False}


@numba.njit(**_NO_RC)
def _walk_kernel(
    q: NDArray[np.float64],
    t: NDArray[np.int64],
    trans: NDArray[np.float64],
    nbr: NDArray,
    b0: NDArray[np.float64],
    b1: NDArray[np.float64],
) -> None:
    """``_walk_one`` for every query from its start triangle ``t[i]``, in place."""
    for i in range(q.shape[0]):
        t[i], b0[i], b1[i] = _walk_one(q[i, 0], q[i, 1], t[i], trans, nbr)


@numba.njit(**_NO_RC)
def _surface_kernel(
    pts: NDArray[np.float64],
    ox: float,
    oy: float,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    raster: NDArray[np.int64],
    trans: NDArray[np.float64],
    nbr: NDArray,
    zt: NDArray[np.float64],
    xy: NDArray[np.float64],
    simplices: NDArray,
    slopes: NDArray[np.float64],
    mode: int,
    t: NDArray[np.int64],
    b0: NDArray[np.float64],
    b1: NDArray[np.float64],
    z: NDArray[np.float64],
    sl: NDArray[np.float64],
) -> None:
    """Locate every query ``pts[i, :2] - (ox, oy)``.

    ``_LOCATE``: ``t`` gets the triangle (-(exit triangle + 1) outside the
    hull) and ``b0, b1`` the coordinates. Otherwise ``z`` gets the height
    (``_height``; ``_NEAREST`` or ``_EXTRAPOLATE`` outside the hull, where
    ``_EXTRAPOLATE`` also gives ``t`` = exit triangle), and ``sl``, when
    sized, the facet's ``slopes``.
    """
    for i in range(pts.shape[0]):
        qx = pts[i, 0] - ox
        qy = pts[i, 1] - oy
        tt, c0, c1 = _walk_one(qx, qy, _start(qx, qy, x0, y0, cell, nx, ny, raster), trans, nbr)
        if mode == _LOCATE:
            t[i] = tt
            b0[i] = c0
            b1[i] = c1
            continue
        ti = tt if tt >= 0 else -tt - 1
        if mode == _EXTRAPOLATE:
            t[i] = ti
        if sl.size:
            sl[i] = slopes[ti]
        z[i] = _height(tt, c0, c1, qx, qy, zt, xy, simplices, mode == _NEAREST)


@numba.njit(**_NO_RC)
def _band_kernel(
    pts: NDArray[np.float64],
    ox: float,
    oy: float,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    raster: NDArray[np.int64],
    trans: NDArray[np.float64],
    nbr: NDArray,
    zt: NDArray[np.float64],
    xy: NDArray[np.float64],
    simplices: NDArray,
    slopes: NDArray[np.float64],
    up: float,
    down: float,
    gain: float,
    cap: float,
    code: NDArray[np.int8],
) -> None:
    """``code[i]`` of point ``pts[i]`` against the surface (see ``Tin.band``)."""
    for i in range(pts.shape[0]):
        qx = pts[i, 0] - ox
        qy = pts[i, 1] - oy
        tt, c0, c1 = _walk_one(qx, qy, _start(qx, qy, x0, y0, cell, nx, ny, raster), trans, nbr)
        r = pts[i, 2] - _height(tt, c0, c1, qx, qy, zt, xy, simplices, True)
        allow = 0.0
        if gain > 0:
            allow = gain * min(slopes[tt if tt >= 0 else -tt - 1], cap)
        if r > up + allow:
            code[i] = ABOVE
        elif r >= -(down + allow):
            code[i] = IN_BAND
        else:
            code[i] = BELOW  # or no height (NaN)


@numba.njit(cache=True, nogil=True)
def _edge_neighbours(simplices: NDArray, n: int) -> tuple[NDArray[np.int32], int, int]:
    """Neighbour triangle opposite each corner of ``simplices`` (-1 on the hull),
    the number of hull edges and the number of vertices in a triangle.

    Directed edges are bucketed by their start vertex (a counting sort); the
    edge opposite corner j runs from corner j + 1 to corner j + 2, and its
    neighbour holds the reversed edge. A directed edge found twice gives a
    hull count of -1.
    """
    m = simplices.shape[0]
    ptr = np.zeros(n + 1, dtype=np.int64)
    for t in range(m):
        for j in range(3):
            ptr[simplices[t, (j + 1) % 3] + 1] += 1
    for v in range(n):
        ptr[v + 1] += ptr[v]
    fill = ptr[:-1].copy()
    to = np.empty(3 * m, dtype=np.int64)
    edge = np.empty(3 * m, dtype=np.int64)
    for t in range(m):
        for j in range(3):
            a = simplices[t, (j + 1) % 3]
            k = fill[a]
            to[k] = simplices[t, (j + 2) % 3]
            edge[k] = 3 * t + j
            fill[a] += 1
    nb = np.full((m, 3), -1, dtype=np.int32)
    vertices = 0
    for v in range(n):
        if ptr[v + 1] > ptr[v]:
            vertices += 1
        for i in range(ptr[v], ptr[v + 1]):
            for k in range(i + 1, ptr[v + 1]):
                if to[i] == to[k]:
                    return nb, -1, vertices
    hull = 0
    for t in range(m):
        for j in range(3):
            a = simplices[t, (j + 1) % 3]
            b = simplices[t, (j + 2) % 3]
            for k in range(ptr[b], ptr[b + 1]):
                if to[k] == a:
                    nb[t, j] = edge[k] // 3
                    break
            else:
                hull += 1
    return nb, hull, vertices


@numba.njit(cache=True, nogil=True)
def _adjacency(
    simplices: NDArray, neighbors: NDArray, n: int
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """CSR adjacency (indptr, indices) of the vertices of a mesh, each row in
    ascending order, as scipy's ``vertex_neighbor_vertices``: every undirected
    edge taken once (from the lower triangle id, or the hull), counted, then
    placed."""
    m = simplices.shape[0]
    deg = np.zeros(n + 1, dtype=np.int32)
    for t in range(m):
        for j in range(3):
            nb = neighbors[t, j]
            if nb < 0 or t < nb:
                deg[simplices[t, (j + 1) % 3] + 1] += 1
                deg[simplices[t, (j + 2) % 3] + 1] += 1
    indptr = np.cumsum(deg).astype(np.int32)
    fill = indptr[:-1].copy()
    indices = np.empty(indptr[n], dtype=np.int32)
    for t in range(m):
        for j in range(3):
            nb = neighbors[t, j]
            if nb < 0 or t < nb:
                a = simplices[t, (j + 1) % 3]
                b = simplices[t, (j + 2) % 3]
                indices[fill[a]] = b
                fill[a] += 1
                indices[fill[b]] = a
                fill[b] += 1
    for v in range(n):
        _insertion_sort(indices[indptr[v] : indptr[v + 1]])
    return indptr, indices


@numba.njit(cache=True, inline="always")
def _insertion_sort(a: NDArray) -> None:
    """Sort the short array ``a`` in place (a vertex's neighbours: about six)."""
    for i in range(1, a.size):
        v = a[i]
        k = i - 1
        while k >= 0 and a[k] > v:
            a[k + 1] = a[k]
            k -= 1
        a[k + 1] = v


# One compiled pass each over the millions of points (support.py): the numpy
# forms gather and combine several full-length temporaries per round.


@numba.njit(cache=True, inline="always")
def _doubled(a: NDArray[np.int64]) -> NDArray[np.int64]:
    """``a`` copied into an array twice as long (the rest unset)."""
    b = np.empty(2 * a.size, dtype=a.dtype)
    b[: a.size] = a
    return b


@numba.njit(cache=True, nogil=True)
def _fans(
    verts: NDArray[np.int64],
    vt: NDArray[np.int64],
    simplices: NDArray,
    neighbors: NDArray,
    used: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], bool]:
    """The triangles around each vertex of ``verts`` (CSR ``tptr``, ``tris``) and
    its neighbour vertices (``nptr``, ``nidx``, rows ascending as ``_adjacency``'s),
    gathered from one triangle holding it (``vt``) across the edges through it.
    False when a vertex's fan does not hold its ``used`` triangles (two fans
    meeting at one vertex): the caller then reads the whole mesh instead."""
    nv = verts.size
    tptr = np.zeros(nv + 1, dtype=np.int64)
    nptr = np.zeros(nv + 1, dtype=np.int64)
    tris = np.empty(8 * nv + 8, dtype=np.int64)
    nidx = np.empty(8 * nv + 8, dtype=np.int64)
    nt = 0
    nn = 0
    ok = True
    for i in range(nv):
        v = verts[i]
        if nt >= tris.size:
            tris = _doubled(tris)
        tris[nt] = vt[v]
        end = nt + 1
        k = nt
        while k < end:
            t = tris[k]
            for j in range(3):
                u = neighbors[t, j]
                if u < 0 or (
                    simplices[u, 0] != v and simplices[u, 1] != v and simplices[u, 2] != v
                ):
                    continue
                seen = False
                for q in range(nt, end):
                    if tris[q] == u:
                        seen = True
                        break
                if not seen:
                    if end >= tris.size:
                        tris = _doubled(tris)
                    tris[end] = u
                    end += 1
            k += 1
        if end - nt != used[v]:
            ok = False
        first = nn
        for q in range(nt, end):
            for j in range(3):
                w = simplices[tris[q], j]
                if w == v:
                    continue
                dup = False
                for p in range(first, nn):
                    if nidx[p] == w:
                        dup = True
                        break
                if not dup:
                    if nn >= nidx.size:
                        nidx = _doubled(nidx)
                    nidx[nn] = w
                    nn += 1
        _insertion_sort(nidx[first:nn])
        nt = end
        tptr[i + 1] = nt
        nptr[i + 1] = nn
    return tptr, tris[:nt], nptr, nidx[:nn], ok


@numba.njit(cache=True)
def _top_of_ground(
    cell: NDArray[np.int64], z: NDArray[np.float64], ground: NDArray[np.bool_], size: int
) -> NDArray[np.float64]:
    """Highest z of the ground points of each cell (-inf when none; NaN propagates as in ``np.maximum.at``)."""
    top = np.full(size, -np.inf)
    for i in range(cell.size):
        if ground[i]:
            v = z[i]
            b = cell[i]
            if v > top[b] or np.isnan(v):
                top[b] = v
    return top


@numba.njit(cache=True)
def _under_top(
    todo: NDArray[np.bool_],
    z: NDArray[np.float64],
    top: NDArray[np.float64],
    cell: NDArray[np.int64],
    tol: float,
) -> NDArray[np.int64]:
    """Indices of the ``todo`` points with ``z <= top[cell] + tol``."""
    out = np.empty(cell.size, dtype=np.int64)
    m = 0
    for i in range(cell.size):
        if todo[i] and z[i] <= top[cell[i]] + tol:
            out[m] = i
            m += 1
    return out[:m].copy()


@numba.njit(cache=True)
def _flagged_in(
    points: NDArray[np.bool_], cells: NDArray[np.bool_], cell: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Indices of the flagged ``points`` lying in flagged ``cells``."""
    out = np.empty(cell.size, dtype=np.int64)
    m = 0
    for i in range(cell.size):
        if points[i] and cells[cell[i]]:
            out[m] = i
            m += 1
    return out[:m].copy()


@numba.njit(cache=True)
def _still_todo(
    may: NDArray[np.bool_],
    ground: NDArray[np.bool_],
    near: NDArray[np.bool_],
    cell: NDArray[np.int64],
) -> NDArray[np.bool_]:
    """``may & ~ground & near[cell]``."""
    out = np.empty(cell.size, dtype=np.bool_)
    for i in range(cell.size):
        out[i] = may[i] and not ground[i] and near[cell[i]]
    return out


@numba.njit(cache=True)
def _extremes(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
) -> NDArray[np.int64]:
    """Increasing indices of the points whose z is the min or max of their cell
    (NaN propagating into a cell's min and max as with ``np.minimum.at``)."""
    n = x.size
    flat = np.empty(n, dtype=np.int64)
    lo = np.full(nx * ny, np.inf)
    hi = np.full(nx * ny, -np.inf)
    for i in range(n):
        b = np.int64(np.floor((y[i] - y0) / cell)) * nx + np.int64(np.floor((x[i] - x0) / cell))
        flat[i] = b
        zi = z[i]
        if zi < lo[b] or np.isnan(zi):
            lo[b] = zi
        if zi > hi[b] or np.isnan(zi):
            hi[b] = zi
    out = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        b = flat[i]
        if z[i] == lo[b] or z[i] == hi[b]:
            out[m] = i
            m += 1
    return out[:m].copy()


@numba.njit(cache=True)
def _top_k_per_group(
    group: NDArray[np.int64], score: NDArray[np.float64], n_groups: int, k: int
) -> NDArray[np.int64]:
    """Rank by rank, in group order, the indices of the ``k`` largest positive
    scores of each group (equal scores: smaller index first)."""
    val = np.empty((n_groups, k))
    idx = np.full((n_groups, k), -1, dtype=np.int64)
    for i in range(group.size):
        s = score[i]
        if not s > 0:
            continue
        g = group[i]
        j = 0
        while j < k and idx[g, j] >= 0 and val[g, j] >= s:
            j += 1
        if j == k:
            continue
        for m in range(k - 1, j, -1):
            val[g, m] = val[g, m - 1]
            idx[g, m] = idx[g, m - 1]
        val[g, j] = s
        idx[g, j] = i
    count = 0
    for g in range(n_groups):
        for r in range(k):
            if idx[g, r] >= 0:
                count += 1
    out = np.empty(count, dtype=np.int64)
    m = 0
    for r in range(k):
        for g in range(n_groups):
            if idx[g, r] >= 0:
                out[m] = idx[g, r]
                m += 1
    return out


@numba.njit(cache=True, nogil=True)
def _judge_kernel(
    indptr: NDArray,
    indices: NDArray,
    test: NDArray[np.int64],
    rows: NDArray[np.int64],
    z: NDArray[np.float64],
    xy: NDArray[np.float64],
    sl: NDArray[np.float64],
    screen_tol: float,
    low_tol: float,
    rim: NDArray[np.bool_],
    rim_len2: float,
    bad: NDArray[np.bool_],
) -> None:
    """``bad[v]`` for each ``test`` vertex v (its neighbours: row ``rows[i]`` of
    the CSR ``indptr``, ``indices`` for ``test[i]``): more than ``screen_tol`` above the
    median of its neighbours' votes, or more than ``low_tol`` (if > 0) below
    the second lowest of their pit votes (see ``screen``). A neighbour u does
    not vote when both ``rim[v]`` and ``rim[u]`` hold and their squared
    distance exceeds ``rim_len2`` (> 0): a sliver along the data's edge.

    With slopes ``sl`` (one row per vertex; none: zero rows), a neighbour u
    votes z_u + g·(v - u) with g the mean of both ends' slopes (the
    trapezoid rule: exact on any quadratic surface, so curved hills are not
    taken for objects), and its pit vote uses u's own slope alone: the plane
    of v's bin, tilted by an outlier at v, would vouch for it.
    """
    with_slopes = sl.shape[0] > 0
    width = 0
    for r in rows:
        width = max(width, indptr[r + 1] - indptr[r])
    votes = np.empty(width)
    pits = np.empty(width)
    for i in range(test.size):
        v = test[i]
        a = indptr[rows[i]]
        deg = indptr[rows[i] + 1] - a
        if deg == 0:
            continue
        m = 0
        for k in range(deg):
            u = indices[a + k]
            d0 = xy[v, 0] - xy[u, 0]
            d1 = xy[v, 1] - xy[u, 1]
            if rim_len2 > 0 and rim[v] and rim[u] and d0 * d0 + d1 * d1 > rim_len2:
                continue
            zu = z[u]
            if with_slopes:
                votes[m] = zu + 0.5 * (sl[u, 0] + sl[v, 0]) * d0 + 0.5 * (sl[u, 1] + sl[v, 1]) * d1
                pits[m] = zu + sl[u, 0] * d0 + sl[u, 1] * d1
            else:
                votes[m] = zu
                pits[m] = zu
            m += 1
        if m == 0:
            continue
        deg = m
        vs = votes[:deg]
        ps = pits[:deg]
        if deg <= _SORT_WIDTH:
            _insertion_sort(vs)
            _insertion_sort(ps)
        else:
            vs.sort()
            ps.sort()
        med = 0.5 * (vs[(deg - 1) // 2] + vs[deg // 2])
        second = ps[min(1, deg - 1)]
        zv = z[v]
        bad[v] = zv - med > screen_tol or (low_tol > 0 and second - zv > low_tol)


# ------------------------------------------------------------ growth (growth.py)


@numba.njit(cache=True)
def _node_slope(
    o: int,
    start: NDArray[np.int64],
    nbr: NDArray[np.int64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    dz: NDArray[np.float64],
    ground: NDArray[np.bool_],
) -> tuple[float, float]:
    """``growth._ground_slopes`` of node ``o`` (its edges ``start[o]:start[o + 1]``),
    summed in edge order as ``np.bincount`` sums them."""
    suu = svv = suv = suz = svz = 0.0
    for e in range(start[o], start[o + 1]):
        if ground[nbr[e]]:
            u, v, w = du[e], dv[e], dz[e]
            suu += u * u
            svv += v * v
            suv += u * v
            suz += u * w
            svz += v * w
    det = suu * svv - suv * suv
    t = suu + svv
    if det > 1e-6 * (t * t):
        return (suz * svv - svz * suv) / det, (svz * suu - suz * suv) / det
    return 0.0, 0.0


@numba.njit(cache=True)
def _grow_rounds(
    ground: NDArray[np.bool_],
    own: NDArray[np.int64],
    nbr: NDArray[np.int64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    dz: NDArray[np.float64],
    limit: NDArray[np.float64],
    limit_below: NDArray[np.float64],
    indptr: NDArray[np.int64],
    adjacent: NDArray[np.int64],
    max_rounds: int,
) -> None:
    """``growth.grow_ground``'s rounds (without ``agree`` and ``reach``) in place on
    ``ground``: the same nodes join in the same round. Only nodes whose ground
    neighbours changed (the new ones and those around them, found through the full
    adjacency ``indptr``, ``adjacent``) get new slopes and try their edges again: the
    others' edges failed last round with the same slopes."""
    n = ground.size
    start = np.zeros(n + 1, dtype=np.int64)
    for e in range(own.size):
        start[own[e] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    gx = np.zeros(n)
    gy = np.zeros(n)
    active = np.flatnonzero(ground)
    mark = np.zeros(n, dtype=np.bool_)
    new = np.empty(n, dtype=np.int64)
    buf = np.empty(n, dtype=np.int64)
    for _ in range(max_rounds):
        for o in active:
            gx[o], gy[o] = _node_slope(o, start, nbr, du, dv, dz, ground)
        m = 0
        for o in active:
            for e in range(start[o], start[o + 1]):
                j = nbr[e]
                if ground[j] or mark[j]:
                    continue
                err = dz[e] - gx[o] * du[e] - gy[o] * dv[e]
                if err <= limit[e] and err >= -limit_below[e]:
                    mark[j] = True
                    new[m] = j
                    m += 1
        if m == 0:
            break
        for i in range(m):
            ground[new[i]] = True
            mark[new[i]] = False
        # Every node whose ground neighbours changed, each once: the new ones and
        # the ground around them.
        count = 0
        for i in range(m):
            v = new[i]
            if not mark[v]:
                mark[v] = True
                buf[count] = v
                count += 1
            for a in range(indptr[v], indptr[v + 1]):
                u = adjacent[a]
                if ground[u] and not mark[u]:
                    mark[u] = True
                    buf[count] = u
                    count += 1
        active = buf[:count].copy()
        for i in range(count):
            mark[active[i]] = False


# ------------------------------------------------------------ raised segments (raised.py)


@numba.njit(cache=True)
def _lower_medians(v: NDArray[np.int64], value: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Per id of ``v`` (0 … n − 1) the lower middle of its ``value`` in ascending
    order (NaN last, equal values in input order: the order of ``np.lexsort((value,
    v))``), 0 where an id has none. A counting sort by id, then an insertion sort of
    each id's few values."""
    start = np.zeros(n + 1, dtype=np.int64)
    for i in range(v.size):
        start[v[i] + 1] += 1
    for k in range(n):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    s = np.empty(v.size)
    for i in range(v.size):
        s[fill[v[i]]] = value[i]
        fill[v[i]] += 1
    out = np.zeros(n)
    for k in range(n):
        a, b = start[k], start[k + 1]
        if a == b:
            continue
        for i in range(a + 1, b):
            x = s[i]
            j = i - 1
            # Moves only past strictly greater values (NaN above every number): stable.
            while j >= a and (s[j] > x or (np.isnan(s[j]) and not np.isnan(x))):
                s[j + 1] = s[j]
                j -= 1
            s[j + 1] = x
        out[k] = s[a + (b - a - 1) // 2]
    return out


@numba.njit(cache=True)
def _near_outline(
    q: NDArray[np.float64],
    a: NDArray[np.float64],
    d: NDArray[np.float64],
    length: NDArray[np.float64],
    band: float,
) -> NDArray[np.bool_]:
    """Whether the least distance of each point of ``q`` to the lines through ``a`` along
    ``d`` (offsets over ``length``) is at most ``band`` (NaN propagating, as numpy's min)."""
    out = np.empty(q.shape[0], dtype=np.bool_)
    for i in range(q.shape[0]):
        best = np.inf
        for e in range(a.shape[0]):
            off = abs((q[i, 0] - a[e, 0]) * d[e, 1] - (q[i, 1] - a[e, 1]) * d[e, 0]) / length[e]
            if off < best or np.isnan(off):
                best = off
                if np.isnan(off):
                    break
        out[i] = best <= band
    return out


# ------------------------------------------------------------ raised segments (raised.py)


@numba.njit(cache=True, inline="always")
def _disc_cells(
    cx: float, cy: float, half: float, lo_x: float, lo_y: float, cell: float
) -> tuple[int, int, int, int]:
    """First and last cell columns and rows the box of a disc (widened by 1 µm) meets."""
    r = half + 1e-6
    return (
        int(np.floor((cx - r - lo_x) / cell)),
        int(np.floor((cx + r - lo_x) / cell)),
        int(np.floor((cy - r - lo_y) / cell)),
        int(np.floor((cy + r - lo_y) / cell)),
    )


@numba.njit(cache=True, nogil=True)
def _ramp_counts(
    points: NDArray[np.float64],
    foot: NDArray[np.float64],
    d: NDArray[np.float64],
    run: NDArray[np.float64],
    rise: NDArray[np.float64],
    centre: NDArray[np.float64],
    lo_x: float,
    lo_y: float,
    cell: float,
    nx: int,
    ny: int,
) -> NDArray[np.int64]:
    """Per step (foot ``foot``, plan vector ``d`` of length ``run``, ``rise``): counts of the
    ``points`` within half the run of the run's centre that lie 20–80 % along it and within
    half the run of its line, as columns: all of them, those on the straight ramp (height
    fraction f within 0.25 of the fraction along), f ≤ 0.25, f ≥ 0.75, 0.25 < f < 0.75.

    One pass over the points through a grid of cells (side ``cell``, corner ``lo``) each
    listing the steps whose disc's box (widened by 1 µm) meets it: no per-step search of a
    dense block's returns."""
    k = foot.shape[0]
    ptr = np.zeros(nx * ny + 1, dtype=np.int64)
    for j in range(k):
        x0, x1, y0, y1 = _disc_cells(centre[j, 0], centre[j, 1], 0.5 * run[j], lo_x, lo_y, cell)
        for ix in range(max(x0, 0), min(x1, nx - 1) + 1):
            for iy in range(max(y0, 0), min(y1, ny - 1) + 1):
                ptr[ix * ny + iy + 1] += 1
    for c in range(nx * ny):
        ptr[c + 1] += ptr[c]
    fill = ptr[:-1].copy()
    disc = np.empty(ptr[-1], dtype=np.int64)
    for j in range(k):
        x0, x1, y0, y1 = _disc_cells(centre[j, 0], centre[j, 1], 0.5 * run[j], lo_x, lo_y, cell)
        for ix in range(max(x0, 0), min(x1, nx - 1) + 1):
            for iy in range(max(y0, 0), min(y1, ny - 1) + 1):
                c = ix * ny + iy
                disc[fill[c]] = j
                fill[c] += 1
    out = np.zeros((k, 5), dtype=np.int64)
    for i in range(points.shape[0]):
        x = points[i, 0]
        y = points[i, 1]
        gx = (x - lo_x) / cell
        gy = (y - lo_y) / cell
        if not (gx >= 0.0 and gx < nx and gy >= 0.0 and gy < ny):
            continue
        c = int(gx) * ny + int(gy)
        for p in range(ptr[c], ptr[c + 1]):
            j = disc[p]
            ex = x - centre[j, 0]
            ey = y - centre[j, 1]
            half = 0.5 * run[j]
            if ex * ex + ey * ey > half * half:
                continue
            u = x - foot[j, 0]
            v = y - foot[j, 1]
            t = (u * d[j, 0] + v * d[j, 1]) / (run[j] * run[j])
            across = abs(u * d[j, 1] - v * d[j, 0]) / run[j]
            if not (t > 0.2 and t < 0.8 and across < half):
                continue
            h = rise[j] if rise[j] != 0 else 1e-9
            f = (points[i, 2] - foot[j, 2]) / h
            out[j, 0] += 1
            if abs(f - t) < 0.25:
                out[j, 1] += 1
            if f <= 0.25:
                out[j, 2] += 1
            if f >= 0.75:
                out[j, 3] += 1
            if f > 0.25 and f < 0.75:
                out[j, 4] += 1
    return out
