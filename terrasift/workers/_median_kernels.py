"""Compiled square median filter (``categories._strided_median``): the values are
replaced by their ranks, and each row's windows slide over a two-level histogram of
ranks, so a window's median costs a few dozen counter reads instead of a selection
over every value of the window. The same values as ``scipy.ndimage.median_filter``
with ``mode="nearest"``. Kept apart from the numpy code so an edit there does not
recompile it (numba's cache follows the source file).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True, nogil=True)
def median_ranks(ranks: NDArray[np.int64], size: int, n: int) -> NDArray[np.int64]:
    """The median rank (the (size² // 2)-th smallest, from 0) over every ``size`` ×
    ``size`` window of ``ranks`` (distinct values 0..n-1), the window of a cell reaching
    ``size // 2`` cells before it and the rest after, cells beyond the edge taking the
    nearest edge cell's rank. The median's bin of 64 ranks is followed from window to
    window, and the median found within it."""
    rows, cols = ranks.shape
    before = size // 2
    after = size - 1 - before
    want = (size * size) // 2  # the rank of the median within a window
    fine = 64
    out = np.empty((rows, cols), dtype=np.int64)
    hist = np.zeros(n, dtype=np.int32)
    chist = np.zeros(n // fine + 1, dtype=np.int32)
    for r in range(rows):
        for dr in range(-before, after + 1):
            rr = min(max(r + dr, 0), rows - 1)
            for dc in range(-before, after + 1):
                v = ranks[rr, min(max(dc, 0), cols - 1)]
                hist[v] += 1
                chist[v // fine] += 1
        bin_ = 0  # the median's bin, and how many values lie in the bins below it
        below = 0
        while below + chist[bin_] <= want:
            below += chist[bin_]
            bin_ += 1
        for c in range(cols):
            if c > 0:  # slide: the column leaving, the column entering
                cl = min(max(c - 1 - before, 0), cols - 1)
                ce = min(max(c + after, 0), cols - 1)
                for dr in range(-before, after + 1):
                    rr = min(max(r + dr, 0), rows - 1)
                    v = ranks[rr, cl]
                    hist[v] -= 1
                    chist[v // fine] -= 1
                    if v // fine < bin_:
                        below -= 1
                    v = ranks[rr, ce]
                    hist[v] += 1
                    chist[v // fine] += 1
                    if v // fine < bin_:
                        below += 1
                while below > want:
                    bin_ -= 1
                    below -= chist[bin_]
                while below + chist[bin_] <= want:
                    below += chist[bin_]
                    bin_ += 1
            seen = below
            v = bin_ * fine
            while seen + hist[v] <= want:
                seen += hist[v]
                v += 1
            out[r, c] = v
        # empty the histograms for the next row: take the last window out
        for dr in range(-before, after + 1):
            rr = min(max(r + dr, 0), rows - 1)
            for dc in range(cols - 1 - before, cols + after):
                v = ranks[rr, min(max(dc, 0), cols - 1)]
                hist[v] -= 1
                chist[v // fine] -= 1
    return out


def median_filter(a: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """``scipy.ndimage.median_filter(a, size=size, mode="nearest")`` of a 2-D array
    without NaN."""
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return a.copy()
    order = np.argsort(a, axis=None, kind="stable")
    ranks = np.empty(a.size, dtype=np.int64)
    ranks[order] = np.arange(a.size)
    med = median_ranks(ranks.reshape(a.shape), int(size), a.size)
    return a.ravel()[order[med]]
