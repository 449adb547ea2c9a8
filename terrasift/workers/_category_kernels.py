"""Compiled per-tile fit of the terrain categories (``categories.category_grids``):
every tile is read, fitted by one plane and the best two-plane ("hinge") model
and measured in one pass, instead of a dozen passes over stacked tile arrays.
Kept apart from the numpy code so an edit there does not recompile it (numba's
cache follows the source file).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True, nogil=True)
def fit_tiles(
    padded: NDArray[np.float64],
    k: int,
    s: int,
    rows: int,
    cols: int,
    xs: NDArray[np.float64],
    ys: NDArray[np.float64],
    hinge: NDArray[np.float64],
    hnorm: NDArray[np.float64],
    gate: float,
    edge_ratio: float,
    explain: float,
    trends: NDArray[np.float64],
) -> tuple[NDArray, ...]:
    """Fit the ``rows`` × ``cols`` tiles of k × k cells starting every ``s`` cells of ``padded``.

    ``xs``, ``ys``: cell-centre coordinates of a tile's k² cells (row-major, metres);
    ``hinge``: (k², 16) hinge regressors with their plane part removed, ``hnorm`` their
    squared norms; ``gate``: one-plane residual RMS above which two planes are tried,
    ``edge_ratio``: share of the one-plane residual they must leave; ``explain``: the
    residual RMS up to which a model explains a tile (its range is the flatness
    height). ``trends``: (m, 2, n) east/north gradients taken off each tile for each of
    m grids (zeros: the tiles as they lie).

    Returns nodata (n,), two (n,), best (n,), c3 (n,), gx, gy, height, relief (m, n)
    and relief of the tiles as they lie (n,).
    """
    n = rows * cols
    kk = k * k
    ne = hinge.shape[1]
    m = trends.shape[0]
    nodata = np.zeros(n, dtype=np.bool_)
    two = np.zeros(n, dtype=np.bool_)
    best = np.zeros(n, dtype=np.int64)
    c3 = np.zeros(n)
    gx = np.zeros((m, n))
    gy = np.zeros((m, n))
    height = np.zeros((m, n))
    relief = np.zeros((m, n))
    lying = np.zeros(n)
    sxx = 0.0
    syy = 0.0
    for c in range(kk):
        sxx += xs[c] * xs[c]
        syy += ys[c] * ys[c]
    z = np.empty(kk)
    r0 = np.empty(kk)
    fit = np.empty(kk)
    proj = np.empty(ne)
    for t in range(n):
        r = (t // cols) * s
        q = (t % cols) * s
        mean = 0.0
        bad = False
        for a in range(k):
            for b in range(k):
                v = padded[r + a, q + b]
                if np.isnan(v):
                    bad = True
                z[a * k + b] = v
                mean += v
        if bad:
            nodata[t] = True
            continue
        mean /= kk
        px = 0.0
        py = 0.0
        for c in range(kk):
            z[c] -= mean
            px += xs[c] * z[c]
            py += ys[c] * z[c]
        ax = px / sxx
        ay = py / syy
        rss0 = 0.0
        for c in range(kk):
            r0[c] = z[c] - ax * xs[c] - ay * ys[c]
            rss0 += r0[c] * r0[c]
        # every hinge's projection at once, each summed over the cells in order
        for e in range(ne):
            proj[e] = 0.0
        for c in range(kk):
            rc = r0[c]
            for e in range(ne):
                proj[e] += rc * hinge[c, e]
        bi = 0
        bg = -1.0
        bp = 0.0
        for e in range(ne):
            p = proj[e]
            g = p * p / hnorm[e]
            if g > bg:
                bg = g
                bi = e
                bp = p
        best[t] = bi
        cc = bp / hnorm[bi]
        c3[t] = cc
        rms0 = np.sqrt(rss0 / kk)
        is_two = rms0 > gate and rss0 - bg <= edge_ratio * rss0
        two[t] = is_two
        left = rss0 - bg if is_two else rss0
        explained = np.sqrt(max(left, 0.0) / kk) <= explain
        # the model's fitted values without the plane's slope (added back per grid)
        for c in range(kk):
            fit[c] = z[c] - r0[c] + (cc * hinge[c, bi] if is_two else 0.0)
        for j in range(m + 1):
            tx = 0.0 if j == m else trends[j, 0, t]
            ty = 0.0 if j == m else trends[j, 1, t]
            hi = -np.inf
            lo = np.inf
            fhi = -np.inf
            flo = np.inf
            for c in range(kk):
                d = tx * xs[c] + ty * ys[c]
                v = z[c] - d
                if v > hi:
                    hi = v
                if v < lo:
                    lo = v
                f = fit[c] - d
                if f > fhi:
                    fhi = f
                if f < flo:
                    flo = f
            rel = (fhi - flo) if explained else (hi - lo)
            if j == m:
                lying[t] = rel
            else:
                gx[j, t] = ax - tx
                gy[j, t] = ay - ty
                height[j, t] = hi - lo
                relief[j, t] = rel
    return nodata, two, best, c3, gx, gy, height, relief, lying
