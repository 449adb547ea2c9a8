"""Terrain objects of a large DTM searched window by window, each object once.

``detect_features`` over a whole survey holds the survey's category grids in one
process. Here each tile (a *core*: a window of DTM cells; the cores partition
the DTM's data) is searched on its core plus a halo, and gives the *pieces*
(objects before joining, sizing and limits) that it owns; ``merge_pieces`` then
joins, sizes and filters all pieces as ``detect_features`` does. Only the pieces
(polygons) of the whole area are held at once.

Why the pieces equal the whole DTM's: every step up to the pieces is local or
works on connected parts of a filter's *support* (tiles marked along rows or
columns, and a rectangle's cover). Categories read the DTM within a regional
window, segments within their longest match, a rectangle cover within its
window; objects are components of marked tiles joined within ``connect_reach``,
a pond's both-way groups are judged on their either-way component, holes are
enclosed by the object, and a short piece is kept by another label within
``near_reach``. So each object depends only on its *closure*: the component of
its filter's support dilated by the connect reach, with enclosed holes filled.
A window's categories and marks equal the whole DTM's at least ``window_reach``
cells inside its cut edges (edges that are not the DTM's own); a closure lying
inside that safe part is a closure of the whole DTM, and its pieces are the
whole DTM's. A piece belongs to the core holding its first tile (in row order):
one core. A closure that touches the core but reaches the unsafe rim is searched
again on a window grown around it, until it lies in the safe part (at worst the
window is the whole DTM), so no object is cut or found twice.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from rasterio import Affine
from scipy import ndimage

from terrasift.workers.categories import Categories, CategoryParams
from terrasift.workers.features import (
    FeatureParams,
    FeatureResult,
    categories_for,
    connect_reach,
    filter_labels,
    grid_key,
    object_options,
)
from terrasift.workers.features.language import Filter, resolve_lengths
from terrasift.workers.features.objects import (
    Feature,
    finish_pieces,
    label_pieces,
    near_reach,
    prepare_labels,
)

#: a window of DTM cells: (row0, col0, row1, col1), ends excluded
Rect = tuple[int, int, int, int]


@dataclass(frozen=True)
class Piece:
    """An object of filter ``filter`` before joining and sizing; ``key`` is its first
    tile (row, col) on that filter's grid over the whole DTM (the order of labels)."""

    filter: int
    key: tuple[int, int]
    feature: Feature


def _tile_cells(cparams: CategoryParams, cell: float) -> int:
    return max(2, int(round(cparams.tile_size / cell)))


def _step_cells(flt: Filter, k: int, cell: float) -> int:
    return k if flt.step is None else max(1, min(k, int(round(flt.step.value / cell))))


def _spacing(flt: Filter, cparams: CategoryParams, cell: float) -> float:
    """Metres between the tiles of ``flt``'s grid (``Categories.spacing``)."""
    k = _tile_cells(cparams, cell)
    return cparams.tile_size * _step_cells(flt, k, cell) / k


def _resolved(flt: Filter, cparams: CategoryParams, cell: float) -> Filter:
    return resolve_lengths(flt, _spacing(flt, cparams, cell))


def _stride(window: float, k: int, cell: float) -> int:
    """Tiles between the samples of a regional median (``categories._strided_median``)."""
    size = max(1, int(round(window / (k * cell))))
    return max(1, size // 16)


def window_align(filters: list[Filter], cparams: CategoryParams, cell: float) -> int:
    """DTM cells a window's origin is a multiple of, so its tile grids, overlapping
    grids and regional medians fall as over the whole DTM."""
    k = _tile_cells(cparams, cell)
    out = k
    for f in filters:
        out = math.lcm(out, _step_cells(f, k, cell))
        if f.detrend is not None:
            out = math.lcm(out, _stride(f.detrend.value, k, cell) * k)
    return out


def window_reach(filters: list[Filter], cparams: CategoryParams, cell: float) -> int:
    """DTM cells inside a window's cut edges beyond which its closures may differ from
    the whole DTM's: the categories' reach (a partial tile; half a regional window
    and its sampling) plus the farthest filter's (longest segment, rectangle window,
    connect and near reach), each in its grid's steps."""
    k = _tile_cells(cparams, cell)
    cats = k
    for f in filters:
        if f.detrend is not None:
            size = max(1, int(round(f.detrend.value / (k * cell))))
            cats = max(cats, (size // 2 + 2 * _stride(f.detrend.value, k, cell) + 2) * k)
    far = 0
    for f in filters:
        r = _resolved(f, cparams, cell)
        tiles = max((seg.longest for seg in r.segments), default=1)
        if r.rectangle is not None:
            tiles += max(int(r.rectangle.width), int(r.rectangle.height))
        tiles += connect_reach(r) + 2
        if r.connect is not None:
            c = r.connect
            tiles += near_reach(
                (c.min_length, c.max_length, c.min_width, c.max_width), r.join, r.join_aligned
            )
        far = max(far, tiles * _step_cells(f, k, cell) + k)
    return cats + far


def _snap(rect: Rect, shape: tuple[int, int], align: int) -> Rect:
    r0, c0, r1, c1 = rect
    return (
        max(0, r0 // align * align),
        max(0, c0 // align * align),
        min(shape[0], r1),
        min(shape[1], c1),
    )


def tile_pieces(
    read: Callable[[int, int, int, int], NDArray],
    shape: tuple[int, int],
    transform: Affine,
    core: Rect,
    filters: list[Filter],
    cparams: CategoryParams,
    params: FeatureParams | None = None,
    halo: int | None = None,
) -> list[Piece]:
    """The pieces ``core`` owns, searched on the core plus ``halo`` cells (default: the
    filters' ``window_reach`` and 32 m for objects across the core's edges) of the DTM
    of ``shape`` cells and ``transform``; ``read(r0, r1, c0, c1)`` gives its cells (NaN
    nodata). ``cparams.noise`` and ``cparams.slope_noise`` must be the whole DTM's."""
    return search_core(read, shape, transform, core, filters, cparams, params, halo)[0]


def search_core(
    read: Callable[[int, int, int, int], NDArray],
    shape: tuple[int, int],
    transform: Affine,
    core: Rect,
    filters: list[Filter],
    cparams: CategoryParams,
    params: FeatureParams | None = None,
    halo: int | None = None,
) -> tuple[list[Piece], Rect]:
    """``tile_pieces`` with the DTM cells the search read (the union of its windows):
    the pieces stay the same as long as those cells do, so a later search of the same
    core can be skipped when no cell of that window changed."""
    if cparams.noise is None or cparams.slope_noise is None:
        raise ValueError("tile_pieces needs the whole DTM's noise and slope noise")
    params = params or FeatureParams()
    cell = abs(transform.a)
    align = window_align(filters, cparams, cell)
    if halo is None:
        halo = window_reach(filters, cparams, cell) + int(np.ceil(32.0 / cell))
    start = _snap((core[0] - halo, core[1] - halo, core[2] + halo, core[3] + halo), shape, align)
    grids: dict[Rect, tuple[Categories, dict]] = {}

    def categories(rect: Rect, flt: Filter) -> Categories:
        key = grid_key(flt)
        # the start window's grids for all filters, a grown one's for one (another
        # filter may have grown to the same window: its grids lack this filter's)
        if rect not in grids or (key is not None and key not in grids[rect][1]):
            todo = filters if rect == start else [flt]
            dtm = read(rect[0], rect[2], rect[1], rect[3])
            for other in [r for r in grids if r != start]:
                del grids[other]
            grids[rect] = categories_for(dtm, cell, todo, cparams)
        cats, stepped = grids[rect]
        return cats if key is None else stepped[key]

    out: list[Piece] = []
    seen = start
    for i, flt in enumerate(filters):
        if flt.connect is None and flt.rectangle is None:
            continue  # tile marks, not objects
        rect = start
        reach = window_reach([flt], cparams, cell)  # this filter's: its grid and its steps
        while True:
            found, grow = _window_pieces(
                categories(rect, flt), flt, i, rect, shape, transform, core, reach, params, cell
            )
            if grow is None:
                out += found
                break
            before, rect = (
                rect,
                _snap(
                    (
                        min(rect[0], grow[0] - reach - 2 * align),
                        min(rect[1], grow[1] - reach - 2 * align),
                        max(rect[2], grow[2] + reach + 2 * align),
                        max(rect[3], grow[3] + reach + 2 * align),
                    ),
                    shape,
                    align,
                ),
            )
            if rect == before:  # the whole DTM is safe everywhere: cannot happen
                raise RuntimeError(f"feature window {rect} cannot grow")
            seen = (
                min(seen[0], rect[0]),
                min(seen[1], rect[1]),
                max(seen[2], rect[2]),
                max(seen[3], rect[3]),
            )
    return out, seen


def _window_pieces(
    cats: Categories,
    flt: Filter,
    index: int,
    rect: Rect,
    shape: tuple[int, int],
    transform: Affine,
    core: Rect,
    reach: int,
    params: FeatureParams,
    cell: float,
) -> tuple[list[Piece], Rect | None]:
    """The pieces of ``flt`` that ``core`` owns in window ``rect``, or the DTM cells the
    window must grow to cover when a closure touching the core is not in its safe part."""
    k = cats.cells_per_tile
    s = cats.step
    flt = resolve_lengths(flt, cats.spacing)
    labels, marks, support = filter_labels(cats, flt)
    assert labels is not None
    rows, cols = labels.shape
    # tiles whose origin lies in the core, and in the safe part (cut edges only)
    origin_r = rect[0] + np.arange(rows) * s
    origin_c = rect[1] + np.arange(cols) * s
    in_core_r = (origin_r >= core[0]) & (origin_r < core[2])
    in_core_c = (origin_c >= core[1]) & (origin_c < core[3])
    lo_r = rect[0] + (reach if rect[0] > 0 else 0)
    hi_r = rect[2] - (reach if rect[2] < shape[0] else 0)
    lo_c = rect[1] + (reach if rect[1] > 0 else 0)
    hi_c = rect[3] - (reach if rect[3] < shape[1] else 0)
    safe_r = (origin_r >= lo_r) & ((origin_r + k <= hi_r) | (rect[2] >= shape[0]))
    safe_c = (origin_c >= lo_c) & ((origin_c + k <= hi_c) | (rect[3] >= shape[1]))

    if flt.rectangle is not None:
        # the cover is exact in the safe part only: beyond it a marked tile may lie
        # in a cover the window cannot see, so it counts as support there
        support = support | (marks & ~(safe_r[:, None] & safe_c[None, :]))
    r = connect_reach(flt)
    closure = ndimage.binary_dilation(support, structure=np.ones((2 * r + 1, 2 * r + 1), bool))
    if flt.rectangle is None:  # a rectangle's objects fill no holes (covers are its objects)
        closure = ndimage.binary_fill_holes(closure)
    comp, n = ndimage.label(closure, structure=np.ones((3, 3), bool))
    boxes = ndimage.find_objects(comp)
    core_tiles = np.zeros(labels.shape, bool)
    core_tiles[np.ix_(in_core_r, in_core_c)] = True
    mine = set(np.unique(comp[core_tiles & closure]).tolist()) - {0}
    complete = np.zeros(n + 1, bool)
    grow: list[Rect] = []
    for c in range(1, n + 1):
        br, bc = boxes[c - 1]
        # one tile of margin: the tiles bordering the closure are judged outside it
        ok = (
            (br.start == 0 or safe_r[br.start - 1])
            and (bc.start == 0 or safe_c[bc.start - 1])
            and (br.stop == rows or safe_r[br.stop])
            and (bc.stop == cols or safe_c[bc.stop])
            and safe_r[br].all()
            and safe_c[bc].all()
        )
        complete[c] = ok
        if not ok and c in mine:
            grow.append(_cells(rect, br, bc, s, k))

    opts = object_options(flt, params)
    limits = opts.get("limits", (None, None, None, None))
    labels, counts, small = prepare_labels(
        labels, limits, opts.get("fill_holes", True), opts.get("join"), opts.get("join_aligned")
    )
    ids, first = np.unique(labels.ravel(), return_index=True)
    keep = np.zeros(counts.size, bool)
    near = near_reach(limits, opts.get("join"), opts.get("join_aligned"))
    lab_boxes = ndimage.find_objects(labels)
    incomplete = closure & ~complete[comp]
    for lab, f in zip(ids.tolist(), first.tolist(), strict=True):
        if lab == 0:
            continue
        fr, fc = divmod(f, cols)
        if not (in_core_r[fr] and in_core_c[fc]) or not complete[comp[fr, fc]]:
            continue
        if near and 2 * counts[lab] < limits[0] and counts[lab] >= 3:
            # kept or dropped by the labels within reach: theirs must be exact too
            br, bc = lab_boxes[lab - 1]
            a0, a1 = max(0, br.start - near), min(rows, br.stop + near)
            b0, b1 = max(0, bc.start - near), min(cols, bc.stop + near)
            ok = safe_r[a0:a1].all() and safe_c[b0:b1].all() and not incomplete[a0:a1, b0:b1].any()
            if not ok:
                grow.append(_cells(rect, slice(a0, a1), slice(b0, b1), s, k))
                for c in np.unique(comp[a0:a1, b0:b1][incomplete[a0:a1, b0:b1]]).tolist():
                    cr, cc = boxes[c - 1]
                    grow.append(_cells(rect, cr, cc, s, k))  # the closures nearby, whole
                continue
        keep[lab] = not small[lab]
    if grow:
        return [], (
            min(g[0] for g in grow),
            min(g[1] for g in grow),
            max(g[2] for g in grow),
            max(g[3] for g in grow),
        )
    owned = np.where(keep[labels], labels, 0)
    wt = transform @ Affine.translation(rect[1], rect[0])
    pieces = label_pieces(
        owned, counts, flt.name, cats.transform(wt), cats.spacing, params.simplify_tiles
    )
    g0, c0 = rect[0] // s, rect[1] // s
    key = {lab: divmod(f, cols) for lab, f in zip(ids.tolist(), first.tolist(), strict=True)}
    return [
        Piece(index, (g0 + key[lab][0], c0 + key[lab][1]), feat) for lab, feat in pieces.items()
    ], None


def _cells(rect: Rect, br: slice, bc: slice, s: int, k: int) -> Rect:
    """DTM cells of the tiles ``br`` × ``bc`` of a window's grid."""
    return (
        rect[0] + br.start * s,
        rect[1] + bc.start * s,
        rect[0] + (br.stop - 1) * s + k,
        rect[1] + (bc.stop - 1) * s + k,
    )


def merge_pieces(
    pieces: list[Piece],
    filters: list[Filter],
    cparams: CategoryParams,
    cell: float,
    params: FeatureParams | None = None,
) -> FeatureResult:
    """Objects of all cores' pieces: per filter (in order), the pieces in the order of
    their first tiles, joined, sized and limited as ``detect_features`` does."""
    params = params or FeatureParams()
    result = FeatureResult()
    by_filter: dict[int, list[Piece]] = {}
    for p in pieces:
        by_filter.setdefault(p.filter, []).append(p)
    for i, flt in enumerate(filters):
        if flt.connect is None and flt.rectangle is None:
            continue
        mine = sorted(by_filter.get(i, []), key=lambda p: p.key)
        r = _resolved(flt, cparams, cell)
        spacing = _spacing(flt, cparams, cell)
        opts = object_options(r, params)
        opts.pop("fill_holes", None)
        opts.pop("simplify_tiles", None)
        limits = opts.pop("limits", (None, None, None, None))
        result.objects += finish_pieces([p.feature for p in mine], spacing, limits, **opts)
    return result
