"""Compiled kernels of the grid method (``mixed_grid``), kept apart from the numpy
code that calls them so an edit there does not make numba compile them again (its
cache follows the source file).

Each kernel does in one pass over the returns what a chain of numpy expressions did
in several, with the same floating-point operations in the same order, so its
results are the same to the bit (no fastmath).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True)
def line_gather(
    key: NDArray[np.int64],
    lut: NDArray[np.int32],
    offsets: NDArray[np.int64],
    r_pad: NDArray[np.float64],
    inv_pad: NDArray[np.float64],
    c_pad: NDArray[np.float64],
    J: NDArray[np.int64],
    R: NDArray[np.float64],
    V: NDArray[np.float64],
    C: NDArray[np.float64],
) -> None:
    """For each offset (row) and return (column): the index of the return at grid key
    ``key + offset`` (``key.size`` where none; the rows of ``J`` only, the first
    offsets) and its range, inverse range and range change across, into ``R``, ``V``,
    ``C`` (offsets × returns). ``lut`` maps every grid key to its return (``key.size``:
    none); an empty one means binary search in the sorted ``key`` (the first of equal
    keys)."""
    n = key.size
    m = offsets.size
    dense = lut.size > 0
    for o in range(m):
        off = offsets[o]
        for i in range(n):
            want = key[i] + off
            if dense:
                j = int(lut[want])
            else:
                lo, hi = 0, n
                while lo < hi:
                    mid = (lo + hi) >> 1
                    if key[mid] < want:
                        lo = mid + 1
                    else:
                        hi = mid
                j = min(lo, n - 1)
                if key[j] != want:
                    j = n
            if o < J.shape[0]:
                J[o, i] = j
            R[o, i] = r_pad[j]
            V[o, i] = inv_pad[j]
            C[o, i] = c_pad[j]


@numba.njit(cache=True)
def spread_of(
    slope: NDArray[np.float64],
    blur: NDArray[np.float64],
    sigma2: float,
    sigmas: float,
    factor: float,
) -> NDArray[np.float64]:
    """sigmas × sqrt(sigma2 + (slope × blur)²) × factor, a NaN slope taken as 0."""
    out = np.empty(slope.size, dtype=np.float64)
    for i in range(slope.size):
        d = slope[i]
        if np.isnan(d):
            d = 0.0
        t = d * blur[i]
        out[i] = sigmas * np.sqrt(sigma2 + t * t) * factor
    return out


@numba.njit(cache=True)
def continued(
    va: NDArray[np.float64], vb: NDArray[np.float64], steps: float
) -> NDArray[np.float64]:
    """Range of the surface through inverse ranges ``va`` (nearer p) and ``vb`` continued
    ``steps`` beyond ``va``: 1 / (va + (va − vb) × steps), infinite where not positive."""
    out = np.empty(va.size, dtype=np.float64)
    for i in range(va.size):
        v = va[i] + (va[i] - vb[i]) * steps
        out[i] = 1.0 / v if v > 0 else np.inf
    return out


@numba.njit(cache=True)
def incidence_cos(
    r: NDArray[np.float64],
    va: NDArray[np.float64],
    vb: NDArray[np.float64],
    across: NDArray[np.float64],
    ra: NDArray[np.float64],
    step: float,
    step_x: float,
) -> NDArray[np.float64]:
    """cos(incidence) at p's beam (range ``r``) of the surface through inverse ranges
    ``va`` and ``vb`` along the axis (tan = r |va − vb| / step) with range change
    ``across`` per beam across it at range ``ra`` (tan = r across / ra² / step_x)."""
    out = np.empty(r.size, dtype=np.float64)
    for i in range(r.size):
        tan_a = r[i] * abs(va[i] - vb[i]) / step
        tan_x = r[i] * across[i] / (ra[i] * ra[i]) / step_x
        out[i] = 1.0 / np.sqrt(1.0 + tan_a * tan_a + tan_x * tan_x)
    return out


@numba.njit(cache=True)
def edge_drops(
    r_out: NDArray[np.float64],
    r_a: NDArray[np.float64],
    r: NDArray[np.float64],
    anchored: NDArray[np.bool_],
    margin: float,
) -> NDArray[np.int64]:
    """Indexes of the returns whose beam at some offset (range ``r_a``) is not
    ``anchored``, lies off the return by more than ``margin`` in range, and whose next
    beam outwards (``r_out``) lies nearer than it by more than ``margin``."""
    out = np.empty(r.size, dtype=np.int64)
    m = 0
    for i in range(r.size):
        if r_out[i] < r_a[i] - margin and not anchored[i] and abs(r_a[i] - r[i]) > margin:
            out[m] = i
            m += 1
    return out[:m]


@numba.njit(cache=True)
def _range_at(q, o, key, lut, stride, r):
    """Range of the return ``o`` beams from return ``q`` along the line (NaN: none)."""
    n = r.size
    w = key[q] + o * stride
    if lut.size:
        j = lut[w]
    else:
        j = np.searchsorted(key, w)
        if j < n and key[j] != w:
            j = n
    return r[j] if j < n else np.nan


@numba.njit(cache=True)
def past_run(
    c: NDArray[np.int64],
    key: NDArray[np.int64],
    lut: NDArray[np.int32],
    stride: int,
    r: NDArray[np.float64],
    blur: NDArray[np.float64],
    a: int,
    sd: int,
    thin: int,
    margin: float,
    sigma: float,
    sigmas: float,
    step: float,
    across: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``mixed_grid._past_thin_run``'s loop over the runs of the returns ``c`` (the beam
    ``a`` = sd × i beams away): the returns off the surface found past a run, and their
    range offsets from it."""
    i = a * sd
    out = np.empty(c.size, dtype=np.int64)
    dev = np.empty(c.size, dtype=np.float64)
    m = 0
    for t in range(c.size):
        q = c[t]
        ra = _range_at(q, a, key, lut, stride, r)
        for L in range(1, thin + 1):
            rl = _range_at(q, sd * (i + L), key, lut, stride, r)
            if not (rl < ra - margin):
                break
            b1 = _range_at(q, sd * (i + L + 1), key, lut, stride, r)
            b2 = _range_at(q, sd * (i + L + 2), key, lut, stride, r)
            v1, v2 = 1.0 / b1, 1.0 / b2
            sd1 = sigmas * np.sqrt(sigma**2 + (np.abs(b1 - b2) * blur[q]) ** 2)
            k = L + 1
            va = v1 + (v1 - v2) * k
            land = np.abs((1.0 / va if va > 0 else np.inf) - ra)
            if not ((b1 > rl + margin) and (land <= sd1 * np.sqrt((k + 1) ** 2 + k**2 + 1))):
                continue
            k = L + 1 + i
            rp = r[q]
            vp = v1 + (v1 - v2) * k
            d = np.abs((1.0 / vp if vp > 0 else np.inf) - rp)
            cos_inc = 1.0 / np.sqrt(1.0 + (rp * np.abs(v1 - v2) / step) ** 2)
            if (d > sd1 * np.sqrt((k + 1) ** 2 + k**2 + 1)) and (d * cos_inc > across):
                out[m] = q
                dev[m] = d
                m += 1
            break
    return out[:m], dev[:m]
