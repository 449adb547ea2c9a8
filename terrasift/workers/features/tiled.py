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

With a cap on that growth, a closure larger than the cap is not searched whole:
marks, covers and labels are exact in the safe part, so each core gives the tiles
of its labels within the core (``Cut``) with the tiles they connect to just across
the core's edges, and ``merge_pieces`` joins the parts into labels before judging
them as a whole (the rules over whole labels add up over parts; holes are those
enclosed within a window or by the joined outline).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from rasterio import Affine
from rasterio.features import rasterize, shapes
from scipy import ndimage
from shapely import affinity
from shapely.geometry import MultiPolygon, Polygon, shape
from shapely.ops import unary_union

from terrasift.workers.categories import NODATA, Categories, CategoryParams
from terrasift.workers.features import (
    DtmHeights,
    FeatureParams,
    FeatureResult,
    Rim,
    apply_yields,
    categories_for,
    clear_counts,
    clear_exempt_tiles,
    clear_kept,
    connect_reach,
    filter_labels,
    grid_key,
    object_options,
    rim_leak,
    rim_sectors,
    rim_sets,
    whole_label_rules,
)
from terrasift.workers.features.language import Filter, resolve_lengths
from terrasift.workers.features.objects import (
    Feature,
    finish_pieces,
    label_pieces,
    near_other,
    near_reach,
    prepare_labels,
    rectangle_size,
    scan_order,
    square_dilation,
)
from terrasift.workers.features.turned import CATEGORY_BANDS, turned_reach

#: a window of DTM cells: (row0, col0, row1, col1), ends excluded
Rect = tuple[int, int, int, int]


@dataclass(frozen=True)
class Cut:
    """The part within one core of a label too large for a capped window: its tiles
    as a polygon in tile indices of the filter's grid over the whole DTM (exact
    integers, unsimplified, holes it encloses within the window filled), what joins
    it to the parts in other cores, and the sums the whole label is judged by."""

    grid: tuple[float, float, float, float, float, float]  # tile indices -> metres
    polygon: Polygon | MultiPolygon
    edge: frozenset[tuple[int, int]]  # its tiles within the connect reach of the core's edge
    links: frozenset[tuple[int, int]]  # the label's tiles just outside the core (other cores')
    near: bool  # another label within ``near_reach`` of one of its tiles
    clear: tuple[float, float, float] | None  # ``clear_counts`` (not flat, clearly, all tiles)
    lines: tuple[frozenset[int], frozenset[int]] | None  # rows, columns (``connect segment``)
    ring: tuple[frozenset[tuple[int, int]], frozenset[tuple[int, int]]] | None = None
    """``surround``: the open ground within its distance of the part's tiles, and the
    tiles of it that are not flat (their unions over the parts are the whole label's)."""
    rim: Rim | None = None
    """``enclosed``: the part's ``Rim`` (the union of the parts' rims, less the tiles of
    the label itself, is the whole label's)."""
    fall: Rim | None = None
    """``isolated``: the part's ``Rim`` with every tile, joined as ``rim``."""
    clear_exempt: float | None = None
    """``clear-share``'s exemption (``clear_exempt_tiles``), the same for every part."""


@dataclass(frozen=True)
class Piece:
    """An object of filter ``filter`` before joining and sizing; ``key`` is its first
    tile (row, col) on that filter's grid over the whole DTM (the order of labels).
    With ``cut``, only the part of a label within one core: ``merge_pieces`` joins
    the parts of all cores into the label first."""

    filter: int
    key: tuple[int, int]
    feature: Feature
    cut: Cut | None = None


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


def category_reach(filters: list[Filter], cparams: CategoryParams, cell: float) -> int:
    """DTM cells inside a window's cut edges beyond which its categories may differ from
    the whole DTM's: a partial tile, or half a regional window and its sampling."""
    k = _tile_cells(cparams, cell)
    cats = k
    for f in filters:
        if f.detrend is not None:
            size = max(1, int(round(f.detrend.value / (k * cell))))
            cats = max(cats, (size // 2 + 2 * _stride(f.detrend.value, k, cell) + 2) * k)
    return cats


def window_reach(filters: list[Filter], cparams: CategoryParams, cell: float) -> int:
    """DTM cells inside a window's cut edges beyond which its closures may differ from
    the whole DTM's: the categories' reach (a partial tile; half a regional window
    and its sampling) plus the farthest filter's (longest segment, rectangle window,
    connect and near reach), each in its grid's steps."""
    k = _tile_cells(cparams, cell)
    cats = category_reach(filters, cparams, cell)
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
        if f.diagonal is not None:  # its turned marks read the DTM around a tile as far as this
            longest = max((seg.longest for seg in r.segments), default=1)
            turned = turned_reach(longest, _step_cells(f, k, cell), k, cell)
            far = max(far, turned + (tiles - longest) * _step_cells(f, k, cell) + k)
    return cats + far


def _block_margin(filters: list[Filter], cparams: CategoryParams, cell: float) -> int:
    """DTM cells a block's categories are read with around it: the categories' reach, or
    a ``diagonal`` filter's turned marks' (``turned_reach``), whichever is farther."""
    k = _tile_cells(cparams, cell)
    out = category_reach(filters, cparams, cell)
    for f in filters:
        if f.diagonal is not None:
            longest = max((seg.longest for seg in _resolved(f, cparams, cell).segments), default=1)
            out = max(out, turned_reach(longest, _step_cells(f, k, cell), k, cell))
    return out


#: DTM cells a side of the blocks a grown window's categories are made in (each read
#: with a margin of the categories' reach): a grown window holds its category grids,
#: never its DTM or the float arrays its categories are computed from
BLOCK_CELLS = 1024

_BANDS = (*CATEGORY_BANDS, "turned")


def blocked_categories(
    read: Callable[[int, int, int, int], NDArray],
    rect: Rect,
    filters: list[Filter],
    cparams: CategoryParams,
    cell: float,
    block: int = BLOCK_CELLS,
) -> tuple[Categories, dict]:
    """``categories_for`` of window ``rect`` (origin aligned to ``window_align``), made
    block by block: each block of ``block`` cells a side is read with a margin of the
    categories' reach and gives the tiles whose origin lies in it, which are those of
    the whole window (the tile grids, regional medians and their samples fall alike:
    the blocks' origins are multiples of the alignment). Memory: one block's DTM and
    float arrays, and the window's uint8 grids."""
    align = window_align(filters, cparams, cell)
    h, w = rect[2] - rect[0], rect[3] - rect[1]
    b = max(align, block // align * align)
    if h <= b and w <= b:
        return categories_for(
            read(rect[0], rect[2], rect[1], rect[3]), cell, filters, cparams, (rect[0], rect[1])
        )
    m = -(-_block_margin(filters, cparams, cell) // align) * align
    first: tuple[Categories, dict] | None = None
    bands: dict[object, dict[str, NDArray]] = {}
    for a0 in range(0, h, b):
        for c0 in range(0, w, b):
            a1, c1 = min(h, a0 + b), min(w, c0 + b)
            ra0, rc0 = max(0, a0 - m), max(0, c0 - m)
            dtm = read(
                rect[0] + ra0, rect[0] + min(h, a1 + m), rect[1] + rc0, rect[1] + min(w, c1 + m)
            )
            cats, stepped = categories_for(
                dtm, cell, filters, cparams, (rect[0] + ra0, rect[1] + rc0)
            )
            del dtm
            first = first or (cats, stepped)
            for key, g in [(None, cats), *stepped.items()]:
                st = g.step
                # the tiles whose origin lies in the block: window tiles tr0:tr1, tc0:tc1
                tr0, tr1, tc0, tc1 = a0 // st, -(-a1 // st), c0 // st, -(-c1 // st)
                fr, fc = (a0 - ra0) // st, (c0 - rc0) // st
                out = bands.setdefault(key, {})
                for name in _BANDS:
                    part = getattr(g, name)
                    if part is None:
                        continue
                    if name not in out:
                        out[name] = np.empty((-(-h // st), -(-w // st)), part.dtype)
                    out[name][tr0:tr1, tc0:tc1] = part[fr : fr + tr1 - tr0, fc : fc + tc1 - tc0]
            del cats, stepped
    assert first is not None

    def whole(key: object, g: Categories) -> Categories:
        made: dict[str, Any] = {n: bands[key][n] for n in _BANDS if getattr(g, n) is not None}
        return replace(g, **made)

    return whole(None, first[0]), {key: whole(key, g) for key, g in first[1].items()}


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
    cap: int | None = None,
) -> list[Piece]:
    """The pieces ``core`` owns, searched on the core plus ``halo`` cells (default: the
    filters' ``window_reach`` and 32 m for objects across the core's edges) of the DTM
    of ``shape`` cells and ``transform``; ``read(r0, r1, c0, c1)`` gives its cells (NaN
    nodata). ``cparams.noise`` and ``cparams.slope_noise`` must be the whole DTM's.
    With ``cap`` the window grows at most ``cap`` cells beyond the halo (``search_core``)."""
    return search_core(read, shape, transform, core, filters, cparams, params, halo, cap)[0]


def search_core(
    read: Callable[[int, int, int, int], NDArray],
    shape: tuple[int, int],
    transform: Affine,
    core: Rect,
    filters: list[Filter],
    cparams: CategoryParams,
    params: FeatureParams | None = None,
    halo: int | None = None,
    cap: int | None = None,
) -> tuple[list[Piece], Rect]:
    """``tile_pieces`` with the DTM cells the search read (the union of its windows):
    the pieces stay the same as long as those cells do, so a later search of the same
    core can be skipped when no cell of that window changed.

    ``cap`` (cells) bounds the window at the core plus the halo (at least the
    filters' reach) plus ``cap`` on each side. An object whose closure spans more
    than ``cap`` cells (a level plain, a road across the survey) is then not
    searched whole: each core gives its label's tiles within the core (``Cut``),
    exact there, and ``merge_pieces`` joins the parts of all cores by the links
    each saw across its edges. Every core judges a closure large or not alike
    (a closure of at most ``cap`` cells that touches a core lies in the safe part
    of that core's largest window), so an object is either whole in one core or
    cut in all that hold it."""
    if cparams.noise is None or cparams.slope_noise is None:
        raise ValueError("tile_pieces needs the whole DTM's noise and slope noise")
    params = params or FeatureParams()
    cell = abs(transform.a)
    align = window_align(filters, cparams, cell)
    if halo is None:
        halo = window_reach(filters, cparams, cell) + int(np.ceil(32.0 / cell))
    start = _snap((core[0] - halo, core[1] - halo, core[2] + halo, core[3] + halo), shape, align)
    limit: Rect | None = None
    if cap is not None:
        ext = max(halo, window_reach(filters, cparams, cell) + 2 * align) + cap
        limit = _snap((core[0] - ext, core[1] - ext, core[2] + ext, core[3] + ext), shape, align)
    grids: dict[Rect, tuple[Categories, dict]] = {}

    def categories(rect: Rect, flt: Filter, every: bool = False) -> Categories:
        """``flt``'s grids on ``rect``, made for ``every`` filter or for ``flt`` alone
        (another filter may have grown to the same window: its grids lack this one's);
        only one window's grids are held at a time."""
        key = grid_key(flt)
        if rect not in grids or (key is not None and key not in grids[rect][1]):
            grids.clear()
            if every:
                dtm = read(rect[0], rect[2], rect[1], rect[3])
                grids[rect] = categories_for(dtm, cell, filters, cparams, (rect[0], rect[1]))
                del dtm
            else:  # a grown window: block by block, so its DTM is never held whole
                grids[rect] = blocked_categories(read, rect, [flt], cparams, cell)
        cats, stepped = grids[rect]
        return cats if key is None else stepped[key]

    found: dict[int, list[Piece]] = {}
    todo: list[tuple[int, Filter, Rect]] = []
    # every filter on the start window first, then the start window's grids go before
    # any window grows: a grown window holds one filter's grids, never the start
    # window's too, so the peak is the larger of the two, not their sum
    for i, flt in enumerate(filters):
        if flt.connect is None and flt.rectangle is None:
            continue  # tile marks, not objects
        reach = window_reach([flt], cparams, cell)  # this filter's: its grid and its steps
        pieces, grow = _window_pieces(
            categories(start, flt, every=True),
            flt,
            i,
            start,
            shape,
            transform,
            core,
            reach,
            params,
            cell,
            cap,
            start == limit,
        )
        if grow is None:
            found[i] = pieces
        else:
            todo.append((i, flt, grow))
    if todo:
        grids.clear()
    seen = start
    for i, flt, grow in todo:
        reach = window_reach([flt], cparams, cell)
        rect = start
        at_limit = rect == limit
        while True:
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
            if limit is not None:
                rect = (
                    max(rect[0], limit[0]),
                    max(rect[1], limit[1]),
                    min(rect[2], limit[2]),
                    min(rect[3], limit[3]),
                )
                # at the limit what is still cut is large: searched in parts
                at_limit = rect in (before, limit)
            if rect == before and not at_limit:  # the whole DTM is safe everywhere
                raise RuntimeError(f"feature window {rect} cannot grow")
            seen = (
                min(seen[0], rect[0]),
                min(seen[1], rect[1]),
                max(seen[2], rect[2]),
                max(seen[3], rect[3]),
            )
            pieces, next_grow = _window_pieces(
                categories(rect, flt),
                flt,
                i,
                rect,
                shape,
                transform,
                core,
                reach,
                params,
                cell,
                cap,
                at_limit,
            )
            if next_grow is None:
                found[i] = pieces
                break
            grow = next_grow
    out = [p for i in sorted(found) for p in found[i]]
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
    cap: int | None = None,
    at_limit: bool = False,
) -> tuple[list[Piece], Rect | None]:
    """The pieces of ``flt`` that ``core`` owns in window ``rect``, or the DTM cells the
    window must grow to cover when a closure touching the core is not in its safe part.
    Closures larger than ``cap`` cells, and at the window's ``at_limit`` every closure
    not in its safe part, give the core's parts of their labels (``Cut``) instead."""
    k = cats.cells_per_tile
    s = cats.step
    flt = resolve_lengths(flt, cats.spacing)
    raw, marks, support = filter_labels(cats, flt, whole=False)
    assert raw is not None
    rows, cols = raw.shape
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
    closure = square_dilation(support, 2 * r + 1)
    if flt.rectangle is None:  # a rectangle's objects fill no holes (covers are its objects)
        closure = ndimage.binary_fill_holes(closure)
    comp, n = ndimage.label(closure, structure=np.ones((3, 3), bool))
    boxes = ndimage.find_objects(comp)
    core_tiles = np.zeros(raw.shape, bool)
    core_tiles[np.ix_(in_core_r, in_core_c)] = True
    mine = set(np.unique(comp[core_tiles & closure]).tolist()) - {0}
    complete = np.zeros(n + 1, bool)
    cut = np.zeros(n + 1, bool)  # closures searched in parts
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
        box = _cells(rect, br, bc, s, k)
        if ok and cap is not None:
            cut[c] = max(box[2] - box[0], box[3] - box[1]) > cap
        elif not ok and c in mine:
            if at_limit:
                cut[c] = True
            else:
                grow.append(box)

    # the rules over whole labels hold for labels whose closure is whole here
    labels = whole_label_rules(raw, cats, flt, support)
    if cut.any():
        labels = np.where(cut[comp] & closure, raw, labels)
    opts = object_options(flt, params)
    limits = opts.get("limits", (None, None, None, None))
    labels, counts, small = prepare_labels(
        labels, limits, opts.get("fill_holes", True), opts.get("join"), opts.get("join_aligned")
    )
    ids, first = np.unique(labels.ravel(), return_index=True)
    keep = np.zeros(counts.size, bool)
    parted = np.zeros(counts.size, bool)
    near = near_reach(limits, opts.get("join"), opts.get("join_aligned"))
    lab_boxes = ndimage.find_objects(labels)
    incomplete = closure & ~complete[comp]
    for lab, f in zip(ids.tolist(), first.tolist(), strict=True):
        if lab == 0:
            continue
        fr, fc = divmod(f, cols)
        if cut[comp[fr, fc]]:
            parted[lab] = True
            continue
        if not (in_core_r[fr] and in_core_c[fc]) or not complete[comp[fr, fc]]:
            continue
        if near and 2 * counts[lab] < limits[0] and counts[lab] >= 3:
            # kept or dropped by the labels within reach: theirs must be exact too
            br, bc = lab_boxes[lab - 1]
            a0, a1 = max(0, br.start - near), min(rows, br.stop + near)
            b0, b1 = max(0, bc.start - near), min(cols, bc.stop + near)
            nearby = incomplete[a0:a1, b0:b1]
            ok = safe_r[a0:a1].all() and safe_c[b0:b1].all() and not nearby.any()
            if not ok and not at_limit:
                grow.append(_cells(rect, slice(a0, a1), slice(b0, b1), s, k))
                for c in np.unique(comp[a0:a1, b0:b1][nearby]).tolist():
                    cr, cc = boxes[c - 1]
                    grow.append(_cells(rect, cr, cc, s, k))  # the closures nearby, whole
                continue
            # at the limit (and near a label searched in parts) the labels nearby count
            # as they are here: one a rule over its whole label drops may still keep it
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
    out = [Piece(index, (g0 + key[lab][0], c0 + key[lab][1]), feat) for lab, feat in pieces.items()]
    if parted.any():
        out += _cut_pieces(
            cats, flt, index, raw, labels, parted, core_tiles, (g0, c0), transform, near, support
        )
    return out, None


def _cut_pieces(
    cats: Categories,
    flt: Filter,
    index: int,
    raw: NDArray[np.int32],
    labels: NDArray[np.int32],
    parted: NDArray[np.bool_],
    core_tiles: NDArray[np.bool_],
    origin: tuple[int, int],
    transform: Affine,
    near: int,
    support: NDArray[np.bool_],
) -> list[Piece]:
    """The core's parts of the labels ``parted`` (searched in parts), ``Cut`` pieces."""
    g0, c0 = origin
    mine = np.where(parted[labels] & core_tiles, labels, 0)
    found = np.unique(mine)
    found = found[found > 0]
    if found.size == 0:
        return []
    n = int(labels.max())
    # what joins a part to the others: the label's tiles on both sides of the core's
    # edge, within the reach at which tiles connect
    w = connect_reach(flt)
    rr, cc = np.nonzero(core_tiles)
    r_lo, r_hi, c_lo, c_hi = rr.min(), rr.max(), cc.min(), cc.max()
    ring = np.zeros(labels.shape, bool)
    ring[max(0, r_lo - w) : r_hi + w + 1, max(0, c_lo - w) : c_hi + w + 1] = True
    inner = np.zeros(labels.shape, bool)
    inner[r_lo + w : r_hi - w + 1, c_lo + w : c_hi - w + 1] = True
    edge_mask = core_tiles & ~inner & (mine > 0)
    link_mask = ring & ~core_tiles & parted[labels] & (labels > 0)
    edges = _tile_sets(labels, edge_mask, origin)
    links = _tile_sets(labels, link_mask, origin)
    close = near_other(labels, near, n + 1) if near else np.zeros(n + 1, bool)
    raw_mine = np.where(mine > 0, raw, 0)  # the rules over whole labels count raw tiles
    clear = None
    if flt.clear_share is not None and cats.clear is not None:
        clear = clear_counts(raw_mine, cats, n)
    segment = flt.connect is not None and flt.rectangle is None and flt.connect.method == "segment"
    rings = _ring_sets(raw_mine, found, cats, support, origin, flt.surround)
    rims = (
        rim_sets(raw_mine, found.tolist(), cats, int(flt.enclosed[0]), origin)
        if flt.enclosed is not None
        else {}
    )
    falls = (
        rim_sets(raw_mine, found.tolist(), cats, int(flt.isolated[0]), origin, every=True)
        if flt.isolated is not None
        else {}
    )
    counts = np.bincount(mine.ravel(), minlength=n + 1)
    ids, first = np.unique(mine.ravel(), return_index=True)
    key = dict(zip(ids.tolist(), first.tolist(), strict=True))
    parts: dict[int, list] = {}
    for geom, value in shapes(
        mine, mask=mine > 0, transform=Affine.translation(c0, g0), connectivity=8
    ):
        parts.setdefault(int(value), []).append(shape(geom))
    grid = cats.transform(transform)
    out = []
    for lab in found.tolist():
        lines = None
        if segment:
            a, b = np.nonzero(raw_mine == lab)
            lines = (frozenset((g0 + a).tolist()), frozenset((c0 + b).tolist()))
        part = Cut(
            (grid.a, grid.b, grid.c, grid.d, grid.e, grid.f),
            unary_union(parts[lab]),
            frozenset(edges.get(lab, ())),
            frozenset(links.get(lab, ())),
            bool(close[lab]),
            None
            if clear is None
            else (
                float(clear[0][lab - 1]),
                float(clear[1][lab - 1]),
                float(clear[2][lab - 1]),
            ),
            lines,
            rings.get(lab),
            rims.get(lab),
            falls.get(lab),
            clear_exempt_tiles(flt, cats),
        )
        fr, fc = divmod(key[lab], labels.shape[1])
        feat = Feature(flt.name, part.polygon, 0.0, 0.0, int(counts[lab]))
        out.append(Piece(index, (g0 + fr, c0 + fc), feat, part))
    return out


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
    *,
    dtm: DtmHeights | None = None,
) -> FeatureResult:
    """Objects of all cores' pieces: per filter (in order), the pieces in the order of
    their first tiles, joined, sized and limited as ``detect_features`` does. ``dtm``
    reads the DTM the pieces were searched on (the heights a ``yield ... deeper`` rule
    compares; required when such a rule can apply)."""
    params = params or FeatureParams()
    result = FeatureResult()
    by_filter: dict[int, list[Piece]] = {}
    for p in pieces:
        by_filter.setdefault(p.filter, []).append(p)
    for i, flt in enumerate(filters):
        if flt.connect is None and flt.rectangle is None:
            continue
        r = _resolved(flt, cparams, cell)
        spacing = _spacing(flt, cparams, cell)
        found = by_filter.get(i, [])
        whole = [p for p in found if p.cut is None]
        whole += _join_cuts([p for p in found if p.cut is not None], r, params)
        mine = sorted(whole, key=lambda p: p.key)
        opts = object_options(r, params)
        opts.pop("fill_holes", None)
        opts.pop("simplify_tiles", None)
        limits = opts.pop("limits", (None, None, None, None))
        result.objects += finish_pieces([p.feature for p in mine], spacing, limits, **opts)
    result.objects = apply_yields(
        result.objects, filters, _tile_cells(cparams, cell) * cell, dtm, cparams.noise
    )
    return result


def _join_cuts(parts: list[Piece], flt: Filter, params: FeatureParams) -> list[Piece]:
    """The labels searched in parts (``Cut``), each joined from its parts in all cores
    (a part's links are tiles of the same label in the parts of other cores) and
    judged as a whole: the rules over whole labels, holes, specks and short pieces
    (``prepare_labels``), the polygon simplified once over the whole outline."""
    if not parts:
        return []
    owner = {t: n for n, p in enumerate(parts) for t in p.cut.edge}  # type: ignore[union-attr]
    parent = list(range(len(parts)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for n, p in enumerate(parts):
        for t in p.cut.links:  # type: ignore[union-attr]
            m = owner.get(t)
            if m is not None:
                a, b = root(n), root(m)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    groups: dict[int, list[Piece]] = {}
    for n, p in enumerate(parts):
        groups.setdefault(root(n), []).append(p)
    opts = object_options(flt, params)
    min_l, _, min_w, _ = opts.get("limits", (None, None, None, None))
    c = flt.connect
    out = []
    for members in groups.values():
        cuts = [p.cut for p in members if p.cut is not None]
        tiles = sum(p.feature.tiles for p in members)
        if min_l is not None and 2 * tiles < min_l and (tiles < 3 or not any(x.near for x in cuts)):
            continue
        if min_w is not None and tiles < 0.5 * min_w * min_w:
            continue
        sums = [x.clear for x in cuts if x.clear is not None]
        if flt.clear_share is not None and sums and len(sums) == len(cuts):
            counted, clear, whole = (math.fsum(v[i] for v in sums) for i in range(3))
            exempt = cuts[0].clear_exempt
            if not clear_kept(counted, clear, whole, flt.clear_share, exempt).all():
                continue
        rings = [x.ring for x in cuts if x.ring is not None]
        if flt.surround is not None and rings and len(rings) == len(cuts):
            around = frozenset[tuple[int, int]]().union(*(v[0] for v in rings))
            busy = frozenset[tuple[int, int]]().union(*(v[1] for v in rings))
            if len(busy) > flt.surround[1] * len(around):
                continue
        rim = _joined_rim(cuts, [x.rim for x in cuts]) if flt.enclosed is not None else None
        if flt.enclosed is not None and rim is not None and rim_sectors(rim) < flt.enclosed[1]:
            continue
        fall = _joined_rim(cuts, [x.fall for x in cuts]) if flt.isolated is not None else None
        if flt.isolated is not None and fall is not None and rim_leak(fall) > flt.isolated[1]:
            continue
        lines = [x.lines for x in cuts if x.lines is not None]
        if c is not None and lines and len(lines) == len(cuts):
            rows = frozenset[int]().union(*(v[0] for v in lines))
            cols = frozenset[int]().union(*(v[1] for v in lines))
            span_r, span_c = max(rows) - min(rows) + 1, max(cols) - min(cols) + 1
            present, span = (len(rows), span_r) if span_r >= span_c else (len(cols), span_c)
            if span - present > c.max_error / 100 * span:
                continue
        geom = unary_union([x.polygon for x in cuts])
        if opts.get("fill_holes", True):  # holes that the cores' edges cut open
            geom = _without_holes(geom)
        if isinstance(geom, MultiPolygon):  # tiles touching at corners: traced as one search's
            geom = _traced(geom)
        if isinstance(geom, MultiPolygon):  # as ``objects.polygons``: corners, bridged gaps
            geom = geom.buffer(1e-3, join_style="mitre").buffer(-1e-3, join_style="mitre")
        if isinstance(geom, MultiPolygon):
            geom = geom.buffer(1, join_style="mitre").buffer(-1, join_style="mitre")
        geom = scan_order(geom, rows_down=True)  # simplified as a whole label's outline
        if params.simplify_tiles > 0:
            geom = geom.simplify(params.simplify_tiles, preserve_topology=True)
        geom = affinity.affine_transform(geom, [*cuts[0].grid[:2], *cuts[0].grid[3:5],
                                                cuts[0].grid[2], cuts[0].grid[5]])  # fmt: skip
        length, width = rectangle_size(geom)
        key = min(p.key for p in members)
        out.append(
            Piece(
                members[0].filter, key, Feature(flt.name, geom, float(length), float(width), tiles)
            )
        )
    return out


def _joined_rim(cuts: list[Cut], parts: list[Rim | None]) -> Rim | None:
    """The whole label's ``Rim`` from its parts' (``parts``, one per part in ``cuts``): the
    union of their tiles less the label's own (another core's part's ring holds them);
    None when some part has none."""
    rims = [v for v in parts if v is not None]
    if not rims or len(rims) < len(cuts):
        return None
    inside = _without_holes(unary_union([x.polygon for x in cuts]))
    around_t = sorted(frozenset[tuple[int, int, int]]().union(*(v[0] for v in rims)))
    if around_t:
        xy = np.array(around_t, dtype=float)
        out_of = ~shapely.contains_xy(inside, xy[:, 1] + 0.5, xy[:, 0] + 0.5)
        around_t = [v for v, o in zip(around_t, out_of.tolist(), strict=True) if o]
    return (
        frozenset(around_t),
        math.fsum(v[1] for v in rims),
        math.fsum(v[2] for v in rims),
        sum(v[3] for v in rims),
    )


def _ring_sets(
    parts: NDArray[np.int32],
    found: NDArray,
    cats: Categories,
    support: NDArray[np.bool_],
    origin: tuple[int, int],
    surround: tuple[int, float] | None,
) -> dict[int, tuple[frozenset[tuple[int, int]], frozenset[tuple[int, int]]]]:
    """Per part (label value in ``parts``): the open ground (tiles with data the filter
    does not mark) within ``surround``'s distance of its tiles, and the tiles of it that
    are not flat, as tile indices over the whole DTM; empty without ``surround``. The
    window holds every tile within the distance of its core (the halo covers the
    connect reach, which covers the distance)."""
    if surround is None:
        return {}
    dist = int(surround[0])
    inc, ori, st = cats.inclination, cats.orientation, cats.state
    open_ground = (inc != NODATA) & ~support
    not_flat = open_ground & ((inc | ori | st) != 0)
    d = 2 * dist + 1
    g0, c0 = origin
    boxes = ndimage.find_objects(parts)
    out = {}
    for lab in found.tolist():
        box = boxes[lab - 1] if lab <= len(boxes) else None
        if box is None:  # only filled holes of the label in this core
            out[lab] = (frozenset[tuple[int, int]](), frozenset[tuple[int, int]]())
            continue
        r0, r1 = max(0, box[0].start - dist), min(parts.shape[0], box[0].stop + dist)
        b0, b1 = max(0, box[1].start - dist), min(parts.shape[1], box[1].stop + dist)
        ring = square_dilation(parts[r0:r1, b0:b1] == lab, d)
        a, b = np.nonzero(ring & open_ground[r0:r1, b0:b1])
        around = frozenset(zip((g0 + r0 + a).tolist(), (c0 + b0 + b).tolist(), strict=True))
        a, b = np.nonzero(ring & not_flat[r0:r1, b0:b1])
        busy = frozenset(zip((g0 + r0 + a).tolist(), (c0 + b0 + b).tolist(), strict=True))
        out[lab] = (around, busy)
    return out


def _tile_sets(
    labels: NDArray[np.int32], mask: NDArray[np.bool_], origin: tuple[int, int]
) -> dict[int, set[tuple[int, int]]]:
    """Per label, its tiles in ``mask`` as (row, col) of the whole DTM's grid."""
    a, b = np.nonzero(mask)
    out: dict[int, set[tuple[int, int]]] = {}
    for lab, r, c in zip(
        labels[a, b].tolist(), (a + origin[0]).tolist(), (b + origin[1]).tolist(), strict=True
    ):
        out.setdefault(lab, set()).add((r, c))
    return out


def _traced(geom: Polygon | MultiPolygon) -> Polygon | MultiPolygon:
    """The union of tile-index polygons as ``objects.polygons`` makes a label's: its tiles
    traced by ``shapes`` with 8-connectivity, then united. A union of parts splits a
    label whose tiles touch at corners only (an island in its own hole) into polygons
    that the corner buffer does not join, where the trace gives one polygon; the
    bridging buffer would then fill its small holes."""
    c0, r0, c1, r1 = (int(round(v)) for v in geom.bounds)
    at = Affine.translation(c0, r0)
    mask = rasterize([geom], out_shape=(r1 - r0, c1 - c0), transform=at, dtype=np.uint8)
    return unary_union(
        [shape(g) for g, _ in shapes(mask, mask=mask > 0, transform=at, connectivity=8)]
    )


def _without_holes(geom: Polygon | MultiPolygon) -> Polygon | MultiPolygon:
    if isinstance(geom, Polygon):
        return Polygon(geom.exterior)
    return unary_union([Polygon(g.exterior) for g in geom.geoms])
