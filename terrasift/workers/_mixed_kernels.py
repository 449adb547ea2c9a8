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
