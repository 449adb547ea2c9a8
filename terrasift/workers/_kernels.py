"""Compiled kernels of the per-bin statistics (``bins``), kept apart from the
numpy code that calls them so an edit there does not make numba compile them
again (its cache follows the source file).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

#: An offset less than this share of a bin below a bin edge counts as on it: coordinates
#: and grid origins are rounded to about 1e-10 m, real points lie 1e-3 m apart or more.
_ON_EDGE = 1e-7


@numba.njit(cache=True)
def _cell_counting_sort(
    x: NDArray[np.float64], y: NDArray[np.float64], cell: float, max_keys: int
) -> NDArray[np.int64]:
    """Stable counting sort of the points by row-major cell key (the key of
    ``cell_order``); an empty array when a coordinate is not finite or the keys
    span more than ``max_keys`` cells (the caller falls back to a radix sort)."""
    n = x.size
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    lo_x = lo_y = np.iinfo(np.int64).max
    hi_x = hi_y = np.iinfo(np.int64).min
    for i in range(n):
        fx = np.floor(x[i] / cell)
        fy = np.floor(y[i] / cell)
        if not (np.isfinite(fx) and np.isfinite(fy)) or abs(fx) > 2.0**52 or abs(fy) > 2.0**52:
            return np.empty(0, dtype=np.int64)
        a = np.int64(fx)
        b = np.int64(fy)
        ix[i] = a
        iy[i] = b
        lo_x = min(lo_x, int(a))
        hi_x = max(hi_x, int(a))
        lo_y = min(lo_y, int(b))
        hi_y = max(hi_y, int(b))
    nx = hi_x - lo_x + 1
    ny = hi_y - lo_y + 1
    if nx > max_keys or ny > max_keys or nx * ny > max_keys:
        return np.empty(0, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        k = (iy[i] - lo_y) * nx + (ix[i] - lo_x)
        ix[i] = k
        start[k + 1] += 1
    for k in range(nx * ny):
        start[k + 1] += start[k]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        k = ix[i]
        order[start[k]] = i
        start[k] += 1
    return order


@numba.njit(cache=True)
def _bounds_kernel(
    x: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[float, float, float, float]:
    """Min and max of ``x`` and of ``y`` (same length: one pass over the rows);
    NaN for both of an array holding a NaN, as numpy's."""
    xmin, xmax, ymin, ymax = np.inf, -np.inf, np.inf, -np.inf
    nan_x = nan_y = False
    for i in range(x.size):
        u = x[i]
        v = y[i]
        xmin = min(xmin, u)
        xmax = max(xmax, u)
        ymin = min(ymin, v)
        ymax = max(ymax, v)
        nan_x |= np.isnan(u)
        nan_y |= np.isnan(v)
    if nan_x:
        xmin = xmax = np.nan
    if nan_y:
        ymin = ymax = np.nan
    return xmin, xmax, ymin, ymax


@numba.njit(cache=True)
def _index_kernel(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    out: NDArray[np.int64],
) -> None:
    """``out[i]`` = row-major bin of point i, -1 outside (and for NaN).

    Truncation equals the floor on the non-negative offsets that can be
    inside, and ``trunc(f) < n`` is ``f < n`` for ``f >= 0``. Bins are
    [lower, upper) edges: a point on a lower edge (centimetre coordinates
    on a cell that divides the anchor, 1.6 m in 240 m) belongs to that bin
    whatever the rounding of ``(x - x0) / cell``, which otherwise differs
    with the block's anchored origin (``_ON_EDGE`` of a bin).
    """
    for i in range(x.size):
        fx = (x[i] - x0) / cell + _ON_EDGE
        fy = (y[i] - y0) / cell + _ON_EDGE
        if fx >= 0 and fy >= 0 and fx < nx and fy < ny:
            out[i] = np.int64(fy) * nx + np.int64(fx)
        else:
            out[i] = -1


@numba.njit(cache=True, inline="always")
def _keep_lower(m: float, low: int, zi: float, i: int) -> tuple[float, int]:
    """A bin's running minimum ``m`` and its point ``low`` with point ``i`` of value
    ``zi`` folded in: a smaller value wins, a tie keeps the earlier point (the first
    one at +inf fills an empty slot), and a NaN poisons the bin as ``np.minimum``
    does. Scalars in and out: a helper taking the arrays costs the loop 5 times
    as much (reference counts of the arrays per call)."""
    if zi < m:
        return zi, i
    if zi == m:
        return m, i if low < 0 else low
    if np.isnan(zi):
        return np.nan, low
    return m, low


@numba.njit(cache=True, inline="always")
def _forget_nan_lows(zmin: NDArray[np.float64], low: NDArray[np.int64]) -> None:
    """A bin whose minimum is NaN has no lowest point."""
    for b in range(zmin.size):
        if np.isnan(zmin[b]):
            low[b] = -1


@numba.njit(cache=True)
def _min_argmin(
    flat: NDArray[np.int64], z: NDArray[np.float64], size: int
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Per bin: minimum of ``z`` (+inf when empty, NaN as ``np.minimum`` propagates it)
    and the smallest index of a point holding it (-1 when none). Points with flat < 0 are skipped."""
    zmin = np.full(size, np.inf)
    low = np.full(size, -1, dtype=np.int64)
    for i in range(flat.size):
        b = flat[i]
        if b < 0:
            continue
        zi = z[i]
        zmin[b], low[b] = _keep_lower(zmin[b], low[b], zi, i)
    _forget_nan_lows(zmin, low)
    return zmin, low


@numba.njit(cache=True)
def _level_sums(
    flat: NDArray[np.int64], z: NDArray[np.float64], size: int
) -> tuple[
    NDArray[np.int64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.int64],
]:
    """Per bin: count, sum of z (in point order, as ``np.bincount``), min, max
    (NaN-propagating like ``np.minimum.at``) and the lowest point (as ``_min_argmin``)."""
    n = np.zeros(size, dtype=np.int64)
    zsum = np.zeros(size)
    zmin = np.full(size, np.inf)
    zmax = np.full(size, -np.inf)
    low = np.full(size, -1, dtype=np.int64)
    for i in range(flat.size):
        b = flat[i]
        if b < 0:
            continue
        zi = z[i]
        n[b] += 1
        zsum[b] += zi
        zmin[b], low[b] = _keep_lower(zmin[b], low[b], zi, i)
        if zi > zmax[b] or np.isnan(zi):
            zmax[b] = zi
    _forget_nan_lows(zmin, low)
    return n, zsum, zmin, zmax, low


@numba.njit(cache=True)
def _squared_deviations(
    flat: NDArray[np.int64], z: NDArray[np.float64], mean: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per bin: sum of (z - mean[bin])² in point order."""
    out = np.zeros(mean.size)
    for i in range(flat.size):
        b = flat[i]
        if b >= 0:
            d = z[i] - mean[b]
            out[b] += d * d
    return out


@numba.njit(cache=True)
def _plane_sums(
    flat: NDArray[np.int64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    cx: NDArray[np.float64],
    cy: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Per bin: count and the sums of u, v, z, u², v², uv, uz, vz (columns 0–7),
    u, v = x, y relative to the bin centre; each summed in point order."""
    size = cx.size
    n = np.zeros(size, dtype=np.int64)
    s = np.zeros((size, 8))
    for i in range(flat.size):
        b = flat[i]
        if b < 0:
            continue
        u = x[i] - cx[b]
        v = y[i] - cy[b]
        zi = z[i]
        n[b] += 1
        s[b, 0] += u
        s[b, 1] += v
        s[b, 2] += zi
        s[b, 3] += u * u
        s[b, 4] += v * v
        s[b, 5] += u * v
        s[b, 6] += u * zi
        s[b, 7] += v * zi
    return n, s


@numba.njit(cache=True)
def _plane_residuals(
    flat: NDArray[np.int64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    cx: NDArray[np.float64],
    cy: NDArray[np.float64],
    c: NDArray[np.float64],
    sx: NDArray[np.float64],
    sy: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Per bin: sum of squared residuals about z = c + sx·u + sy·v, the smallest
    residual and the first point holding it (as ``_min_argmin``)."""
    size = cx.size
    ss = np.zeros(size)
    rmin = np.full(size, np.inf)
    low = np.full(size, -1, dtype=np.int64)
    for i in range(flat.size):
        b = flat[i]
        if b < 0:
            continue
        u = x[i] - cx[b]
        v = y[i] - cy[b]
        r = z[i] - c[b]
        r -= sx[b] * u
        r -= sy[b] * v
        ss[b] += r * r
        rmin[b], low[b] = _keep_lower(rmin[b], low[b], r, i)
    _forget_nan_lows(rmin, low)
    return ss, rmin, low
