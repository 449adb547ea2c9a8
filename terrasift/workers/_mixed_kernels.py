"""Compiled kernels of the grid method (``mixed_grid``), kept apart from the numpy
code that calls them so an edit there does not make numba compile them again (its
cache follows the source file).

Each kernel does in one pass over the returns what a chain of numpy expressions did
in several, with the same floating-point operations in the same order, so its
results are the same to the bit (no fastmath); a value no later test reads (the
incidence where p lies on the anchor's surface) is not computed.
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


@numba.njit(cache=True, error_model="numpy")
def anchor_pass(
    r: NDArray[np.float64],
    ra: NDArray[np.float64],
    ra1: NDArray[np.float64],
    ra2: NDArray[np.float64],
    va: NDArray[np.float64],
    va1: NDArray[np.float64],
    va2: NDArray[np.float64],
    ca: NDArray[np.float64],
    blur: NDArray[np.float64],
    i: int,
    sigma2: float,
    sigmas: float,
    spread0: float,
    f1: float,
    fi: float,
    fit3: bool,
    flat_tol: float,
    c3scale: float,
    margin: float,
    step: float,
    step_x: float,
    across: float,
    max_gap: float,
    half: float,
    off_end: NDArray[np.bool_],
    met: NDArray[np.bool_],
    off_blend: NDArray[np.bool_],
) -> tuple[NDArray[np.bool_], ...]:
    """The tests of the beam ``i`` beams from each return p on one side of a line
    (``mixed_grid._mixed_along``): the beam's range, inverse range and range change
    across at offsets i, i + 1, i + 2 (``ra``.., ``va``.., ``ca``), p's range ``r`` and
    angle blur ``blur`` (in steps). Settings: the range variance ``sigma2`` and
    ``sigmas``; ``spread0`` the tolerance of two returns on one surface, ``f1`` and
    ``fi`` the scatter factors of a surface continued one and ``i`` beams on; with
    ``fit3`` a face-on anchor (three beams within ``flat_tol``) is continued by the
    line through its three beams, its scatter times ``c3scale``; ``across`` the least
    offset across a surface; ``half`` half the footprint in beams.

    Returns (anchored, ok, near, far, front, hidden): the beam is on a surface; and p
    lies off it; ok and nearer / farther than p by more than the margin within
    max_gap (its surface continued to p, or itself); p behind it by more than margin +
    step × range (a one-beam front's candidates); ok and nearer, beyond max_gap.
    Updates ``off_end`` (ok within max_gap), ``off_blend`` (off by more than the
    surface could pull it, where no anchor on this side was met before) and ``met``.
    """
    n = r.size
    anchored = np.zeros(n, dtype=np.bool_)
    ok = np.zeros(n, dtype=np.bool_)
    near = np.zeros(n, dtype=np.bool_)
    far = np.zeros(n, dtype=np.bool_)
    front = np.empty(n, dtype=np.bool_)
    hidden = np.zeros(n, dtype=np.bool_)
    fi_ = float(i)
    for k in range(n):
        rk, a, a1, a2 = r[k], ra[k], ra1[k], ra2[k]
        front[k] = rk - a * (1.0 + step) > margin
        v, v1, v2 = va[k], va1[k], va2[k]
        # on a surface: the line through the outer two continues through it
        w = v1 + (v1 - v2) * 1.0
        ext = 1.0 / w if w > 0 else np.inf
        d = abs(a1 - a2)
        if np.isnan(d):
            d = 0.0
        t = d * blur[k]
        three = abs(ext - a) <= sigmas * np.sqrt(sigma2 + t * t) * f1
        if not (three or abs(a1 - a) <= spread0):
            continue  # no anchor: none of the rest holds
        anchored[k] = True
        # off its surface, continued to p's beam (each value computed only where needed)
        w = v + (v - v1) * fi_
        dev = abs((1.0 / w if w > 0 else np.inf) - rk)
        d = abs(a - a1)
        if np.isnan(d):
            d = 0.0
        t = d * blur[k]
        sp = sigmas * np.sqrt(sigma2 + t * t) * fi
        if fit3 and three and abs(a - a2) <= flat_tol and abs(a - rk) > margin:
            v3 = (v + v1 + v2) / 3.0 - (v2 - v) / 2.0 * (i + 1)
            dev = abs((1.0 / v3 if v3 > 0 else np.inf) - rk)
            sp = sp * c3scale
        o = False
        if dev > sp:
            tan_a = rk * abs(v - v1) / step
            tan_x = rk * ca[k] / (a * a) / step_x
            o = dev * (1.0 / np.sqrt(1.0 + tan_a * tan_a + tan_x * tan_x)) > across
        if o:
            ok[k] = True
            gap = abs(a - rk)
            if np.isnan(gap):
                gap = dev
            elif not np.isnan(dev):
                gap = min(gap, dev)
            within = gap < max_gap
            near[k] = a < rk - margin and within
            far[k] = a > rk + margin and within
            hidden[k] = a < rk - margin and not within
            if a < rk + max_gap and within:
                off_end[k] = True
                if not met[k]:
                    gg = v - v1
                    vc = v + gg * fi_
                    pulled = abs(1.0 / (vc - gg * half) - 1.0 / vc)
                    if dev > sp + pulled:
                        off_blend[k] = True
        if a < rk + max_gap:
            met[k] = True
    return anchored, ok, near, far, front, hidden


@numba.njit(cache=True)
def behind_both(
    r: NDArray[np.float64],
    r0: NDArray[np.float64],
    r1: NDArray[np.float64],
    margin: float,
    max_gap: float,
) -> NDArray[np.int64]:
    """Indices of the returns (range ``r``) behind which both beams ``r0`` and ``r1`` lie
    by more than ``margin`` and less than ``max_gap`` (NaN: no beam)."""
    n = r.size
    out = np.empty(n, dtype=np.int64)
    m = 0
    for k in range(n):
        d0 = r0[k] - r[k]
        d1 = r1[k] - r[k]
        if d0 > margin and d1 > margin and d0 < max_gap and d1 < max_gap:
            out[m] = k
            m += 1
    return out[:m].copy()


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
