"""Stage 1: find a filter's segments along rows (west→east) and columns (north→south).

Every row is searched at once. A segment is a sequence of subsegments, each a
run of ``min..max`` tiles of one class (any of its categories), with up to
``maxerrors`` tiles that do not match. Matching works on tile boundaries b and
keeps, for every boundary and every prefix S1..Si of the pattern, the set of
total lengths of matches of that prefix ending at b as bits of a uint64
(segments are at most 63 tiles; a uint32 for one under 32). Subsegment i extends
prefix i-1 by every admissible run length L at once, so a pass costs O(Σ max_len)
array operations whatever the row count; segments that begin with the same
subsegments share those passes. The chosen match at an end boundary is the longest
within the segment's total limits; it is then traced back from the pattern's
end to place the subsegments (the seed's end-first matching), and the tiles of
the subsegments not marked ``exclude`` are marked. A compiled pass
(``_search_kernels.search_lines``) does the same row by row, extending a prefix only
from the boundaries where it matched; the array passes (``compiled=False``) are its
reference.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from terrasift.workers.categories import NODATA, Categories
from terrasift.workers.features._search_kernels import search_lines
from terrasift.workers.features.language import (
    CategorySpec,
    Filter,
    Segment,
    SubSegment,
    ValueSet,
    resolve_lengths,
    transform_segment,
)


@lru_cache(maxsize=256)
def _lut(vs: ValueSet) -> NDArray[np.bool_]:
    """Which of the 256 byte values ``vs`` allows (NODATA never); shared, not to be written."""
    lut = np.zeros(256, dtype=bool)
    for v in range(255):
        lut[v] = vs.allows(v)
    lut.flags.writeable = False
    return lut


def _arrays(cats: Categories) -> tuple[NDArray[np.uint8], ...]:
    """The bands a category tests: inclination, orientation, state, height, lying-height, clear,
    rise, grade."""
    relief = cats.relief10 if cats.relief10 is not None else cats.height10
    lying = cats.lying10 if cats.lying10 is not None else relief
    clear = cats.clear
    if clear is None:  # without the band: every tile that is not flat
        clear = ((cats.inclination | cats.orientation | cats.state) != 0).astype(np.uint8)
    # without the rise band: the inclination (flat tiles rise nowhere)
    rise = cats.rise if cats.rise is not None else cats.inclination
    # without the grade band: any tile with an inclination is past every noise margin
    grade = cats.grade
    if grade is None:
        grade = np.where(cats.inclination == 0, 0, 254).astype(np.uint8)
    return (cats.inclination, cats.orientation, cats.state, relief, lying, clear, rise, grade)


def category_mask(
    cats: Categories | tuple[Any, ...],
    spec: CategorySpec,
    looks: dict[tuple[int, ValueSet], NDArray[np.bool_]] | None = None,
) -> NDArray[np.bool_]:
    """Tiles matching one category spec; nodata tiles match nothing, even under ``not``.
    ``looks`` keeps each band's look-up by value set for these ``cats``: a filter's
    categories test the same value sets again and again (a road's level strip and
    its bounding tiles), and each look-up reads the whole band."""
    if isinstance(cats, Categories):
        cats = _arrays(cats)
    looks = {} if looks is None else looks

    def look(i: int, vs: ValueSet) -> NDArray[np.bool_]:
        key = (i, vs)
        if key not in looks:
            looks[key] = _lut(vs)[cats[i]]
        return looks[key]

    inc = cats[0]
    m = look(0, spec.inclination) & look(2, spec.state) & look(1, spec.orientation)
    for i, (name, test) in enumerate(
        (("height", spec.height), ("lying-height", spec.lying_height)), start=3
    ):
        if test.values is not None:
            if len(cats) <= i or cats[i] is None:
                raise ValueError(f"a filter tests {name} but the categories carry no heights")
            m &= look(i, test)
    if spec.clear:
        if len(cats) <= 5 or cats[5] is None:
            raise ValueError("a filter tests clear but the categories carry no clear band")
        m &= cats[5] == 1
    if spec.rise.values is not None:
        if len(cats) <= 6 or cats[6] is None:
            raise ValueError("a filter tests rise but the categories carry no rise band")
        m &= look(6, spec.rise)
    if spec.grade.values is not None:
        m &= look(7, spec.grade)
    if spec.negate:
        m = ~m
    return m & (inc != NODATA)


def class_mask(
    cats, sub: SubSegment, looks: dict[tuple[int, ValueSet], NDArray[np.bool_]] | None = None
) -> NDArray[np.bool_]:
    """Tiles matching any category of a subsegment (``looks`` as ``category_mask``)."""
    out = np.zeros(cats[0].shape, dtype=bool)
    for spec in sub.categories:
        out |= category_mask(cats, spec, looks)
    return out


def search_rows(
    cats: tuple[NDArray, ...],
    seg: Segment,
    band: int = 512,
    masks: dict[tuple[CategorySpec, ...], NDArray[np.bool_]] | None = None,
    sums: dict[tuple[tuple[CategorySpec, ...], int], NDArray[np.integer]] | None = None,
    prefixes: dict[tuple[tuple[SubSegment, ...], int], NDArray[np.unsignedinteger]] | None = None,
    shared: set[tuple[SubSegment, ...]] | None = None,
    looks: dict[tuple[int, ValueSet], NDArray[np.bool_]] | None = None,
    compiled: bool = True,
) -> NDArray[np.bool_]:
    """Marks of ``seg`` (already inverted/rotated as searched) along every row, west→east.

    Rows are independent, so they go through in bands of ``band`` rows to bound
    memory (the length sets take 8 bytes per tile and subsegment). ``masks``
    keeps the class masks of these ``cats`` by subsegment categories, and ``sums``
    their mismatch counts along each band's rows, so a class repeated across
    segments (a road's level strip) is matched and counted once. ``prefixes`` keeps
    the matches of the leading subsegments in ``shared`` (runs of subsegments that
    begin more than one segment), so segments that start alike match that start once;
    ``looks`` the bands' look-ups by value set (``category_mask``), kept with ``masks``.

    ``compiled`` (the default) searches each row in one compiled pass
    (``_search_kernels.search_lines``); False runs the array passes of ``_search_band``,
    the reference it is tested against (the same marks).
    """
    masks = {} if masks is None else masks
    sums = {} if sums is None else sums
    keys = []
    for sub in seg.subsegments:
        if sub.categories not in masks:
            masks[sub.categories] = ~class_mask(cats, sub, looks)
        keys.append(sub.categories)
    nrows = cats[0].shape[0]
    out = []
    if compiled:
        subs = seg.subsegments
        lens = [np.array([int(getattr(u, n)) for u in subs], np.int64) for n in _LIMITS]
        skip = np.array([u.exclude for u in subs], dtype=np.bool_)
        lo, hi = max(1, int(seg.min_total or 1)), int(seg.longest)
        for r in range(0, nrows, band):
            stacked = np.stack([masks[key][r : r + band] for key in keys]).view(np.uint8)
            out.append(search_lines(stacked, *lens, skip, lo, hi))
        return out[0] if len(out) == 1 else np.concatenate(out)
    for r in range(0, nrows, band):
        mism = []
        for key in keys:
            if (key, r) not in sums:
                miss = masks[key][r : r + band]
                # counts rise along a row, so differences of them never go below 0
                small = miss.shape[1] < np.iinfo(np.uint16).max
                cm = np.zeros((miss.shape[0], miss.shape[1] + 1), np.uint16 if small else np.int32)
                np.cumsum(miss, axis=1, out=cm[:, 1:])
                sums[(key, r)] = cm
            mism.append(sums[(key, r)])
        out.append(_search_band(mism, seg, prefixes, shared, r))
    return out[0] if len(out) == 1 else np.concatenate(out)


#: the run limits of a subsegment, in the order ``search_lines`` takes them
_LIMITS = ("min_len", "max_len", "max_errors")


def _search_band(
    mism: list[NDArray[np.integer]],
    seg: Segment,
    prefixes: dict[tuple[tuple[SubSegment, ...], int], NDArray[np.unsignedinteger]] | None = None,
    shared: set[tuple[SubSegment, ...]] | None = None,
    band_row: int = 0,
) -> NDArray[np.bool_]:
    """Marks of ``seg`` along rows, given each subsegment's mismatch prefix counts:
    ``mism[i][:, b]`` is the number of tiles in [0, b) not matching subsegment i.
    The matches of a leading run of subsegments in ``shared`` are taken from and
    kept in ``prefixes`` (by the run and ``band_row``)."""
    nrows, nb = mism[0].shape
    ncols = nb - 1
    subs = seg.subsegments

    # match lengths as bits: 32 of them hold a segment up to 31 tiles long, in half the memory
    word = np.uint32 if seg.longest < 32 else np.uint64
    one = word(1)
    prefix = [np.ones((nrows, nb), dtype=word)]  # E_0: the empty match, length 0, at every boundary
    for i, (sub, cm) in enumerate(zip(subs, mism, strict=True)):
        lead = subs[: i + 1]
        kept = None if prefixes is None else prefixes.get((lead, band_row))
        if kept is not None and kept.dtype == word:
            prefix.append(kept)
            continue
        prev = prefix[-1]
        cur = np.zeros_like(prev)
        every = int(cm[:, -1].max(initial=0)) <= sub.max_errors  # no run has too many misses
        for length in range(sub.min_len, sub.max_len + 1):
            if length == 0:
                cur |= prev
                continue
            if length >= nb:
                break
            run = np.left_shift(prev[:, : nb - length], word(length))
            if not every:
                if sub.max_errors == 0:
                    ok = cm[:, length:] == cm[:, : nb - length]
                else:
                    ok = (cm[:, length:] - cm[:, : nb - length]) <= sub.max_errors
                np.multiply(run, ok, out=run)
            np.bitwise_or(cur[:, length:], run, out=cur[:, length:])
        prefix.append(cur)
        if prefixes is not None and shared and lead in shared:
            prefixes[(lead, band_row)] = cur

    lo = max(1, seg.min_total or 1)
    hi = seg.longest
    allowed = word(((1 << (hi + 1)) - 1) ^ ((1 << lo) - 1))
    final = prefix[-1] & allowed
    rr, bb = np.nonzero(final)
    marks = np.zeros((nrows, ncols), dtype=bool)
    if rr.size == 0:
        return marks
    fin = final[rr, bb]
    total = np.zeros(rr.size, dtype=np.int64)
    for t in range(hi, lo - 1, -1):  # longest admissible match
        has = ((fin >> word(t)) & one).astype(bool) & (total == 0)
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
            good &= ((prev[r, s] >> rm.astype(word)) & one).astype(bool)
            chosen[idx[good]] = length
        start = end - chosen
        if not sub.exclude:
            np.add.at(diff, (rr, start), 1)
            np.add.at(diff, (rr, end), -1)
        remaining -= chosen
        end = start
    marks = np.cumsum(diff, axis=1)[:, :ncols] > 0
    return marks


def _shared_leads(segs: list[Segment]) -> set[tuple[SubSegment, ...]]:
    """Leading runs of subsegments that begin more than one of ``segs`` (a road's
    segments start with the same bounding tile and strip)."""
    seen: dict[tuple[SubSegment, ...], int] = {}
    for seg in segs:
        for i in range(1, len(seg.subsegments)):
            lead = seg.subsegments[:i]
            seen[lead] = seen.get(lead, 0) + 1
    return {lead for lead, n in seen.items() if n > 1}


def search_filter(
    cats: Categories, flt: Filter, band: int = 512, compiled: bool = True
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Horizontal and vertical marks of all segments of ``flt`` on the tile grid.

    Rows (then columns) go through in bands of ``band`` lines, every segment over one
    band before the next, so the class masks and mismatch counts the segments share
    are kept for one band only. ``compiled`` as ``search_rows``."""
    flt = resolve_lengths(flt, cats.spacing)
    arrays = _arrays(cats)
    h = np.zeros(cats.shape, dtype=bool)
    v = np.zeros(cats.shape[::-1], dtype=bool)
    for marks, grid, turn, way in (
        (h, arrays, 0, "horizontal"),
        (v, tuple(np.ascontiguousarray(a.T) for a in arrays), 1, "vertical"),
    ):
        segs = [transform_segment(g, turn) for g in flt.segments if g.direction in ("both", way)]
        shared = _shared_leads(segs)
        for r in range(0, grid[0].shape[0], band):
            part = tuple(a[r : r + band] for a in grid)
            masks: dict[tuple[CategorySpec, ...], NDArray[np.bool_]] = {}
            sums: dict[tuple[tuple[CategorySpec, ...], int], NDArray[np.integer]] = {}
            prefixes: dict[tuple[tuple[SubSegment, ...], int], NDArray[np.unsignedinteger]] = {}
            looks: dict[tuple[int, ValueSet], NDArray[np.bool_]] = {}
            for seg in segs:
                marks[r : r + band] |= search_rows(
                    part, seg, band, masks, sums, prefixes, shared, looks, compiled
                )
    v = np.ascontiguousarray(v.T)
    if (
        flt.diagonal is not None and cats.turned is not None
    ):  # marks of the turned tiles (``turned``)
        h |= (cats.turned & 1) > 0
        v |= (cats.turned & 2) > 0
    return h, v
