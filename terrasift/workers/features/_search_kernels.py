"""Compiled row search of one segment (``search.search_rows``): the same length sets as
bits as the array passes of ``search._search_band``, row by row: a subsegment's runs
ending at a boundary are taken only from the boundaries where the pattern before it
matched, and stop at the first that holds too many misses (the misses of a run only
grow with its length), instead of passing over every row for every length. Kept apart from
the numpy code so an edit there does not recompile it (numba's cache follows the source
file).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True, nogil=True)
def search_lines(
    miss: NDArray[np.uint8],
    min_len: NDArray[np.int64],
    max_len: NDArray[np.int64],
    max_errors: NDArray[np.int64],
    exclude: NDArray[np.bool_],
    lo: int,
    hi: int,
) -> NDArray[np.bool_]:
    """Marks of a segment along every row of ``miss`` ((subsegments, rows, cols), 1 where a
    tile does not match the subsegment's class): subsegment i is a run of
    ``min_len[i]..max_len[i]`` tiles with at most ``max_errors[i]`` misses; a match is
    ``lo..hi`` tiles in all (hi ≤ 63); at each end boundary the longest match is traced
    back from the pattern's end, each subsegment taking its longest run, and the tiles
    of the subsegments not ``exclude``d are marked."""
    nsub, nrows, ncols = miss.shape
    nb = ncols + 1
    marks = np.zeros((nrows, ncols), dtype=np.bool_)
    prefix = np.empty((nsub + 1, nb), dtype=np.uint64)
    cm = np.empty((nsub, nb), dtype=np.int64)
    diff = np.empty(nb, dtype=np.int64)
    before = np.empty(nb, dtype=np.int64)
    one = np.uint64(1)
    allowed = np.uint64(0)
    for t in range(lo, hi + 1):
        allowed |= one << np.uint64(t)
    for r in range(nrows):
        last = 0
        for b in range(nb):
            prefix[0, b] = one  # the empty match, length 0, at every boundary
        for i in range(nsub):
            a, z, me = min_len[i], max_len[i], max_errors[i]
            cm[i, 0] = 0  # misses of subsegment i's class before each boundary
            for b in range(ncols):
                cm[i, b + 1] = cm[i, b] + miss[i, r, b]
            last = -1  # the boundaries where prefix i has a match, each to the one before
            first = -1
            for b in range(nb):
                before[b] = last
                if prefix[i, b] != 0:
                    last = b
                    if first < 0:
                        first = b
            if last < 0:  # no match of the prefix in this row: none of the segment
                break
            # runs of a..z tiles extend the prefix's matches to boundaries first+a..last+z
            b0, b1 = min(nb, first + a), min(nb, last + z + 1)
            for b in range(b0):
                prefix[i + 1, b] = 0
            for b in range(b1, nb):
                prefix[i + 1, b] = 0
            for b in range(b0, b1):
                acc = np.uint64(0)
                # the runs ending at b, shortest first, that start where prefix i matched
                p = b - a
                if p >= 0 and prefix[i, p] == 0:
                    p = before[p]
                while p >= 0:
                    length = b - p
                    if length > z or cm[i, b] - cm[i, p] > me:
                        break  # a longer run misses as much or more
                    if length < 64:
                        acc |= prefix[i, p] << np.uint64(length)
                    p = before[p]
                prefix[i + 1, b] = acc
        found = False
        if last < 0:
            continue
        for b in range(nb):
            diff[b] = 0
        for b in range(nb):
            fin = prefix[nsub, b] & allowed
            if fin == 0:
                continue
            found = True
            total = hi
            while (fin >> np.uint64(total)) & one == 0:
                total -= 1
            end = b
            remaining = total
            for i in range(nsub - 1, -1, -1):
                chosen = -1
                for length in range(max_len[i], min_len[i] - 1, -1):  # prefer long runs
                    start = end - length
                    rem = remaining - length
                    if start < 0 or rem < 0:
                        continue
                    if cm[i, end] - cm[i, start] > max_errors[i]:
                        continue
                    if (prefix[i, start] >> np.uint64(rem)) & one:
                        chosen = length
                        break
                start = end - chosen
                if not exclude[i]:
                    diff[start] += 1
                    diff[end] -= 1
                remaining -= chosen
                end = start
        if found:
            run = 0
            for c in range(ncols):
                run += diff[c]
                marks[r, c] = run > 0
    return marks
