"""Stage 1: find a filter's segments along rows (west→east) and columns (north→south).

Every row is searched at once. A segment is a sequence of subsegments, each a
run of ``min..max`` tiles of one class (any of its categories), with up to
``maxerrors`` tiles that do not match. Matching works on tile boundaries b and
keeps, for every boundary and every prefix S1..Si of the pattern, the set of
total lengths of matches of that prefix ending at b as bits of a uint64
(segments are at most 63 tiles). Subsegment i extends prefix i-1 by every
admissible run length L at once, so a pass costs O(Σ max_len) array operations
whatever the row count. The chosen match at an end boundary is the longest
within the segment's total limits; it is then traced back from the pattern's
end to place the subsegments (the seed's end-first matching), and the tiles of
the subsegments not marked ``exclude`` are marked.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from terrasift.workers.categories import NODATA, Categories
from terrasift.workers.features.language import (
    CategorySpec,
    Filter,
    Segment,
    SubSegment,
    ValueSet,
    transform_segment,
)


def _lut(vs: ValueSet) -> NDArray[np.bool_]:
    lut = np.zeros(256, dtype=bool)
    for v in range(255):
        lut[v] = vs.allows(v)
    return lut


def category_mask(
    cats: Categories | tuple[NDArray, NDArray, NDArray], spec: CategorySpec
) -> NDArray[np.bool_]:
    """Tiles matching one category spec; nodata tiles match nothing, even under ``not``."""
    inc, ori, st = (
        (cats.inclination, cats.orientation, cats.state) if isinstance(cats, Categories) else cats
    )
    m = _lut(spec.inclination)[inc] & _lut(spec.state)[st] & _lut(spec.orientation)[ori]
    if spec.negate:
        m = ~m
    return m & (inc != NODATA)


def class_mask(cats, sub: SubSegment) -> NDArray[np.bool_]:
    """Tiles matching any category of a subsegment."""
    out = np.zeros(cats[0].shape, dtype=bool)
    for spec in sub.categories:
        out |= category_mask(cats, spec)
    return out


def search_rows(cats: tuple[NDArray, ...], seg: Segment, band: int = 512) -> NDArray[np.bool_]:
    """Marks of ``seg`` (already inverted/rotated as searched) along every row, west→east.

    Rows are independent, so they go through in bands of ``band`` rows to bound
    memory (the length sets take 8 bytes per tile and subsegment).
    """
    nrows = cats[0].shape[0]
    if nrows <= band:
        return _search_band(cats, seg)
    return np.concatenate(
        [_search_band(tuple(a[r : r + band] for a in cats), seg) for r in range(0, nrows, band)]
    )


def _search_band(cats: tuple[NDArray, ...], seg: Segment) -> NDArray[np.bool_]:
    inc = cats[0]
    nrows, ncols = inc.shape
    nb = ncols + 1
    subs = seg.subsegments
    # mismatch prefix counts per subsegment: mism[:, b] = mismatches in tiles [0, b)
    mism = []
    for sub in subs:
        bad = ~class_mask(cats, sub)
        cm = np.zeros((nrows, nb), dtype=np.int32)
        np.cumsum(bad, axis=1, out=cm[:, 1:])
        mism.append(cm)

    one = np.uint64(1)
    prefix = [
        np.ones((nrows, nb), dtype=np.uint64)
    ]  # E_0: the empty match, length 0, at every boundary
    for sub, cm in zip(subs, mism, strict=True):
        prev = prefix[-1]
        cur = np.zeros_like(prev)
        for length in range(sub.min_len, sub.max_len + 1):
            if length == 0:
                cur |= prev
                continue
            if length >= nb:
                break
            ok = (cm[:, length:] - cm[:, : nb - length]) <= sub.max_errors
            cur[:, length:] |= np.where(
                ok, prev[:, : nb - length] << np.uint64(length), np.uint64(0)
            )
        prefix.append(cur)

    lo = max(1, seg.min_total or 1)
    hi = seg.longest
    allowed = np.uint64(((1 << (hi + 1)) - 1) ^ ((1 << lo) - 1))
    final = prefix[-1] & allowed
    rr, bb = np.nonzero(final)
    marks = np.zeros((nrows, ncols), dtype=bool)
    if rr.size == 0:
        return marks
    fin = final[rr, bb]
    total = np.zeros(rr.size, dtype=np.int64)
    for t in range(hi, lo - 1, -1):  # longest admissible match
        has = ((fin >> np.uint64(t)) & one).astype(bool) & (total == 0)
        total[has] = t

    # trace back from the pattern's end, placing each subsegment
    diff = np.zeros((nrows, ncols + 1), dtype=np.int32)
    end = bb.copy()
    remaining = total.copy()
    for i in range(len(subs) - 1, -1, -1):
        sub, cm, prev = subs[i], mism[i], prefix[i]
        chosen = np.full(rr.size, -1, dtype=np.int64)
        for length in range(sub.max_len, sub.min_len - 1, -1):  # prefer long runs
            todo = chosen < 0
            if not todo.any():
                break
            start = end - length
            rem = remaining - length
            ok = todo & (start >= 0) & (rem >= 0)
            idx = np.nonzero(ok)[0]
            if idx.size == 0:
                continue
            s, e, r, rm = start[idx], end[idx], rr[idx], rem[idx]
            good = (cm[r, e] - cm[r, s]) <= sub.max_errors
            good &= ((prev[r, s] >> rm.astype(np.uint64)) & one).astype(bool)
            chosen[idx[good]] = length
        start = end - chosen
        if not sub.exclude:
            np.add.at(diff, (rr, start), 1)
            np.add.at(diff, (rr, end), -1)
        remaining -= chosen
        end = start
    marks = np.cumsum(diff, axis=1)[:, :ncols] > 0
    return marks


def search_filter(cats: Categories, flt: Filter) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Horizontal and vertical marks of all segments of ``flt`` on the tile grid."""
    arrays = (cats.inclination, cats.orientation, cats.state)
    arrays_t = tuple(np.ascontiguousarray(a.T) for a in arrays)
    h = np.zeros(cats.shape, dtype=bool)
    v = np.zeros(cats.shape, dtype=bool)
    for seg in flt.segments:
        if seg.direction in ("both", "horizontal"):
            h |= search_rows(arrays, transform_segment(seg, 0))
        if seg.direction in ("both", "vertical"):
            v |= search_rows(arrays_t, transform_segment(seg, 1)).T
    return h, v
