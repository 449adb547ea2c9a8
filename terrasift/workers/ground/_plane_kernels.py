"""Compiled kernel of the half-disc test (``halfdisc``): the least-squares planes of a
point's neighbours and of each half-disc of them, one point at a time, kept apart from
the numpy code that calls it so an edit there does not make numba compile it again.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True)
def _solve3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``a`` x = ``b`` for one 3 × 3 system: Gaussian elimination with partial pivoting
    (LAPACK's ``gesv`` order; ``a`` and ``b`` are overwritten)."""
    for c in range(3):
        p = c
        for r in range(c + 1, 3):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if p != c:
            for j in range(3):
                a[c, j], a[p, j] = a[p, j], a[c, j]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, 3):
            f = a[r, c] / a[c, c]
            for j in range(c + 1, 3):
                a[r, j] -= f * a[c, j]
            b[r] -= f * b[c]
    x = np.empty(3)
    for c in range(2, -1, -1):
        s = b[c]
        for j in range(c + 1, 3):
            s -= a[c, j] * x[j]
        x[c] = s / a[c, c]
    return x


@numba.njit(cache=True)
def half_planes(
    d: NDArray[np.float64], u: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per row of offsets ``d`` (m, k, 3) and plane p (0: all k; 1 + h: the neighbours
    with offset · ``u[h]`` ≥ 0): height of the origin above the LS plane, its residual
    deviation (n − 3 degrees of freedom) and the count of points; each (p, m)."""
    m, k = d.shape[0], d.shape[1]
    planes = u.shape[0] + 1
    hh = np.empty((planes, m))
    dd = np.empty((planes, m))
    nn = np.empty((planes, m))
    a = np.empty((3, 3))
    b = np.empty(3)
    s = np.empty(10)
    for i in range(m):
        for p in range(planes):
            s[:] = 0.0
            for j in range(k):
                x, y, z = d[i, j, 0], d[i, j, 1], d[i, j, 2]
                if p > 0 and x * u[p - 1, 0] + y * u[p - 1, 1] < 0:
                    continue
                s[0] += 1.0
                s[1] += x
                s[2] += y
                s[3] += x * x
                s[4] += x * y
                s[5] += y * y
                s[6] += z
                s[7] += x * z
                s[8] += y * z
                s[9] += z * z
            a[0, 0], a[0, 1], a[0, 2] = s[0] + 1e-9, s[1], s[2]
            a[1, 0], a[1, 1], a[1, 2] = s[1], s[3] + 1e-9, s[4]
            a[2, 0], a[2, 1], a[2, 2] = s[2], s[4], s[5] + 1e-9
            b[0], b[1], b[2] = s[6], s[7], s[8]
            c = _solve3(a, b)
            ssr = max(s[9] - (c[0] * s[6] + c[1] * s[7] + c[2] * s[8]), 0.0)
            hh[p, i] = -c[0]
            dd[p, i] = np.sqrt(ssr / max(s[0] - 3.0, 1.0))
            nn[p, i] = s[0]
    return hh, dd, nn
