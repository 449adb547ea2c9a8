"""A filter's marks from tiles turned by 45°, set back on the filter's own grid (``diagonal``).

A filter searches rows and columns of the tile grid (Sjövall §2.1), so a strip is
crossed squarely only when it runs near a grid axis; across a strip at 45° to the
axes a row meets each shoulder obliquely, stretched by √2 and split between tiles
that each hold part of the step. On tiles turned by 45° the rows and columns run
along the grid's diagonals, so every strip lies within 22.5° of an axis of one grid
or the other.

The turned DTM is the DTM sampled (bilinear) on cells of the same size whose axes
run along the diagonals; its lattice is fixed to the whole DTM's first cell (the
window's ``origin``), so a window of the DTM gives the same turned tiles, and the
same marks at least the filter's reach inside its edges, as the whole DTM does. Each
tile of the filter's grid takes the marks of the turned tile whose centre lies
nearest to its own: bit 1 a turned row's, bit 2 a turned column's; where the DTM's
gradients around the tile run nearer the grid's own axes than its diagonals (the
strip is the filter grid's to cross), the turned marks are not taken: crossed at
more than 22.5° from square, a narrow ditch's banks or the level ground beside a
ridge's foot look like a road's bounds to the turned tiles.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from terrasift.workers.categories import Categories, CategoryParams, category_grids
from terrasift.workers.features.language import Filter, Segment, transform_segment
from terrasift.workers.features.search import _arrays, class_mask, search_filter

_R2 = math.sqrt(2.0)

#: metres either side of a tile over which ``diagonal_ground`` reads the DTM's gradients:
#: from any tile of a road's level strip (at most 12 m across, the road filter's widest)
#: to beyond both shoulders (up to ~2 m each in the feature family), 6 + 2 m
ACROSS_M = 8.0
#: the turned tiles' marks are kept where the gradients run within this of a diagonal
#: (each grid takes the strips nearer its own axes; at 30°, on seen seed 57 the level
#: ground at 16° to the grid between a ditch and a ridge's foot made a false road)
LIMIT_DEG = 22.5


def turned_reach(longest: int, step: int, k: int, cell: float) -> int:
    """DTM cells around a tile within which its turned marks read the DTM (in any
    direction, so along the grid's axes too): the longest segment (``longest`` tiles of
    ``step`` cells) through the nearest turned tile (under a step away), a tile, the
    sampling, and the window ``diagonal_ground`` reads."""
    return (longest + 1) * step + k + 2 + int(round(ACROSS_M / cell)) + 1


def _turned_frame(
    shape: tuple[int, int], origin: tuple[int, int], step: int
) -> tuple[float, float, int, int]:
    """First turned cell (u0, w0: multiples of ``step``, in cells) and the turned
    array's size covering a window of ``shape`` cells whose first cell is ``origin``."""
    r0, c0 = origin
    r1, c1 = r0 + shape[0] - 1, c0 + shape[1] - 1
    us = [(r + c) / _R2 for r, c in ((r0, c0), (r1, c1))]
    ws = [(c - r) / _R2 for r, c in ((r1, c0), (r0, c1))]
    u0 = math.floor(us[0] / step) * step
    w0 = math.floor(ws[0] / step) * step
    return u0, w0, int(math.ceil(us[1] - u0)) + 1, int(math.ceil(ws[1] - w0)) + 1


def turned_dtm(
    dtm: NDArray, origin: tuple[int, int], step: int
) -> tuple[NDArray[np.float64], float, float]:
    """The DTM on turned cells (rows along u = (r + c)/√2, columns along w = (c − r)/√2,
    in cells of the whole DTM; NaN outside the window or next to nodata), and the first
    turned cell's u, w."""
    u0, w0, nu, nw = _turned_frame(dtm.shape, origin, step)
    out = np.empty((nu, nw))
    src = np.asarray(dtm, dtype=np.float64)
    w = w0 + np.arange(nw)
    band = 256
    for a in range(0, nu, band):
        u = u0 + np.arange(a, min(nu, a + band))[:, None]
        r = (u - w) / _R2 - origin[0]
        c = (u + w) / _R2 - origin[1]
        out[a : a + u.shape[0]] = ndimage.map_coordinates(
            src, [r, c], order=1, mode="constant", cval=np.nan, prefilter=False
        )
    return out, u0, w0


def turned_marks(
    dtm: NDArray,
    cell: float,
    params: CategoryParams,
    cats: Categories,
    flt: Filter,
    origin: tuple[int, int] = (0, 0),
) -> NDArray[np.uint8]:
    """Marks of ``flt``'s segments searched on tiles turned by 45° (same size and step as
    ``cats``, the filter's grid on ``dtm``), on ``cats``' tiles: bit 1 along a turned row,
    bit 2 along a turned column. ``params`` carries the DTM's noise and slope noise."""
    k, s = cats.cells_per_tile, cats.step
    tdtm, u0, w0 = turned_dtm(dtm, origin, s)
    step_m = None if cats.step_cells is None else s * cell
    tcats = category_grids(tdtm, cell, params, step_m, [None])[0]
    del tdtm
    marked = _search_blocks(tcats, _strips_at_least(flt))
    # each tile of cats: the turned tile whose centre is nearest to its centre
    half = (k - 1) / 2
    r = origin[0] + np.arange(cats.shape[0]) * s + half
    c = origin[1] + np.arange(cats.shape[1]) * s + half
    u = (r[:, None] + c[None, :]) / _R2
    w = (c[None, :] - r[:, None]) / _R2
    p = np.rint((u - u0 - half) / s).astype(np.int64)
    q = np.rint((w - w0 - half) / s).astype(np.int64)
    inside = (p >= 0) & (p < marked.shape[0]) & (q >= 0) & (q < marked.shape[1])
    out = np.zeros(cats.shape, dtype=np.uint8)
    out[inside] = marked[p[inside], q[inside]]
    out[cats.nodata | ~diagonal_ground(dtm, cats, cell)] = 0
    return out


def _strips_at_least(flt: Filter) -> Filter:
    """The resolved filter as searched on the turned tiles: every subsegment that is not
    excluded (the strip) at least ``diagonal`` tiles long."""
    n = int(flt.diagonal or 0)
    segs = tuple(
        replace(
            g,
            subsegments=tuple(
                u
                if u.exclude
                else replace(u, min_len=max(int(u.min_len), n), max_len=max(int(u.max_len), n))
                for u in g.subsegments
            ),
        )
        for g in flt.segments
    )
    return replace(flt, segments=segs, diagonal=None)


def diagonal_ground(dtm: NDArray, cats: Categories, cell: float) -> NDArray[np.bool_]:
    """Tiles of ``cats`` where the DTM's gradients around them (the structure tensor over
    a square ``ACROSS_M`` metres either side) run within ``LIMIT_DEG`` of a diagonal of
    the grid: a strip there is crossed more squarely by the turned tiles' rows and
    columns than by the grid's own."""
    gy, gx = (np.nan_to_num(g) for g in np.gradient(np.asarray(dtm, dtype=np.float64), cell))
    size = 2 * int(round(ACROSS_M / cell)) + 1
    mx = ndimage.uniform_filter(gx, size, mode="nearest")
    my = ndimage.uniform_filter(gy, size, mode="nearest")
    jxx = ndimage.uniform_filter(gx * gx, size, mode="nearest") - mx * mx
    jyy = ndimage.uniform_filter(gy * gy, size, mode="nearest") - my * my
    jxy = ndimage.uniform_filter(gx * gy, size, mode="nearest") - mx * my
    k, s = cats.cells_per_tile, cats.step
    r = np.minimum(np.arange(cats.shape[0]) * s + k // 2, dtm.shape[0] - 1)
    c = np.minimum(np.arange(cats.shape[1]) * s + k // 2, dtm.shape[1] - 1)
    d = (jxx - jyy)[np.ix_(r, c)]
    e = 2 * jxy[np.ix_(r, c)]
    # the tensor's axis at angle t from the grid's: cos 4t = (d^2 - e^2) / (d^2 + e^2)
    lim = math.cos(math.radians(4 * (45 - LIMIT_DEG)))
    return d * d - e * e <= lim * (d * d + e * e)


def _candidates(
    tcats: Categories, segs: tuple[Segment, ...], axis: int
) -> NDArray[np.bool_] | None:
    """Tiles where, along ``axis`` (0: rows), a run of some segment's first strip (its
    first subsegment not excluded) could begin: the next ``min_len`` tiles miss its class
    at most ``max_errors`` times. Every match holds such a run, so lines without one
    cannot match. None when a segment has no strip to test."""
    arrays = _arrays(tcats)
    looks: dict = {}
    out = np.zeros(tcats.shape, dtype=bool)
    tested = set()  # segments whose strips are alike (a road's) are tested once
    for seg in segs:
        # columns are searched on the transposed bands with the segment turned a quarter
        seg = transform_segment(seg, axis)
        strip = next((u for u in seg.subsegments if not u.exclude and u.min_len > 0), None)
        if strip is None:
            return None
        n = int(strip.min_len)
        if (strip.categories, n, strip.max_errors) in tested:
            continue
        tested.add((strip.categories, n, strip.max_errors))
        miss = ~class_mask(arrays, strip, looks)
        if axis == 0:  # runs along rows: count along columns
            cs = np.zeros((miss.shape[0], miss.shape[1] + 1), dtype=np.int32)
            np.cumsum(miss, axis=1, out=cs[:, 1:])
            if n <= miss.shape[1]:
                out[:, : miss.shape[1] - n + 1] |= cs[:, n:] - cs[:, :-n] <= strip.max_errors
        else:
            cs = np.zeros((miss.shape[0] + 1, miss.shape[1]), dtype=np.int32)
            np.cumsum(miss, axis=0, out=cs[1:])
            if n <= miss.shape[0]:
                out[: miss.shape[0] - n + 1] |= cs[n:] - cs[:-n] <= strip.max_errors
    return out


def _search_blocks(tcats: Categories, flt: Filter, band: int = 128) -> NDArray[np.uint8]:
    """``search_filter`` marks (bit 1 rows, bit 2 columns) of the turned grid. Half of it
    lies outside the DTM (a square turned by 45° in its bounding box), and on inclined
    ground most lines hold no level strip: only lines where a strip's run could begin
    (``_candidates``) are searched, ``band`` of them at a time, each band over the
    stretch from its first to its last such run and a margin of the longest segment
    (every match holds a run and is at most that long), then columns alike."""
    m = max((seg.longest for seg in flt.segments), default=1) + 1
    valid = ~tcats.nodata
    out = np.zeros(tcats.shape, dtype=np.uint8)
    ways: tuple[tuple[int, Literal["horizontal", "vertical"], str], ...] = (
        (1, "horizontal", "vertical"),
        (2, "vertical", "horizontal"),
    )
    for bit, way, other in ways:
        segs = tuple(replace(g, direction=way) for g in flt.segments if g.direction != other)
        one = replace(flt, segments=segs)
        axis = 0 if way == "horizontal" else 1
        across = tcats.shape[1 - axis]
        cand = _candidates(tcats, segs, axis)
        if cand is None:
            cand = valid
        lines = np.flatnonzero(cand.any(axis=1 - axis))
        for a0 in range(0, lines.size, band):
            idx = lines[a0 : a0 + band]
            where = np.flatnonzero((cand[idx] if axis == 0 else cand[:, idx]).any(axis=axis))
            b0, b1 = max(0, int(where[0]) - m), min(across, int(where[-1]) + 1 + m)
            box = (idx, slice(b0, b1)) if axis == 0 else (slice(b0, b1), idx)
            part = replace(
                tcats,
                **{
                    n_: getattr(tcats, n_)[box]
                    for n_ in CATEGORY_BANDS
                    if getattr(tcats, n_) is not None
                },
            )
            h, v = search_filter(part, one)
            out[box] |= (h if axis == 0 else v).astype(np.uint8) * np.uint8(bit)
    return out


#: the category grids a filter's search reads (the turned marks are not among them)
CATEGORY_BANDS = (
    "inclination",
    "orientation",
    "state",
    "height10",
    "relief10",
    "lying10",
    "clear",
    "rise",
    "grade",
)
