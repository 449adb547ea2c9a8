"""Terrain objects from categories with the seed's filter language (DESIGN §5.8).

A filter's segments are searched along rows and columns (``search``), the
marks are combined and connected into objects (``connect``), and objects become
polygons with length and width (``objects``). Filters without a connect or
rectangle step (``flat``) give a tile raster instead of objects.

Example::

    filters = [load_filter(n) for n in builtin_filter_names()]
    cats, stepped = categories_for(dtm, 0.5, filters)
    result = detect_features(cats, filters, dtm_transform, cats.tile_size, stepped=stepped)
    fc = features_geojson(result, "EPSG:32633", job_id="j1", to_wgs84=True)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from pydantic import Field
from rasterio import Affine
from scipy import ndimage
from shapely.geometry import MultiPolygon, Polygon, mapping
from shapely.geometry.polygon import orient

from terrasift.errors import ParameterError
from terrasift.workers.categories import (
    NODATA,
    Categories,
    CategoryParams,
    category_grids,
    measure_noise,
    measure_slope_noise,
    regional_gradient,
)
from terrasift.workers.features import connect as _connect
from terrasift.workers.features.edges import sides as edge_sides
from terrasift.workers.features.edges import unbounded
from terrasift.workers.features.language import (
    Filter,
    Length,
    Metres,
    format_filter,
    parse_filter,
    resolve_lengths,
)
from terrasift.workers.features.objects import (
    Feature,
    _measured,
    finish_pieces,
    objects_from_labels,
    rectangle_size,
    square_dilation,
)
from terrasift.workers.features.search import search_filter
from terrasift.workers.features.turned import turned_marks
from terrasift.workers.registry import StageParams, register

__all__ = [
    "DtmHeights",
    "Feature",
    "FeatureParams",
    "FeatureResult",
    "Filter",
    "apply_yields",
    "builtin_filter_names",
    "categories_for",
    "check_filters",
    "detect_features",
    "features_geojson",
    "format_filter",
    "grid_key",
    "grid_keys",
    "load_filter",
    "parse_filter",
    "resolve_filters",
    "resolve_lengths",
]

#: the extra category grid a filter runs on: (step, detrend window) in metres, None for none
GridKey = tuple[float | None, float | None]

_BUILTIN = ("ditch", "ridge", "hill", "pond", "flat", "flat-area", "road")
#: shipped filters a job names to run (``features=ditch-shallow,...``); not in ``all``
_OPTIONAL = ("ditch-shallow",)


class FeatureParams(StageParams):
    """Parameters of feature detection."""

    simplify_tiles: float = Field(0.5, ge=0, le=5)
    """Polygon simplification tolerance in tiles."""


@dataclass
class FeatureResult:
    """Objects of filters with a connect/rectangle step; tile marks of the others."""

    objects: list[Feature] = field(default_factory=list)
    marked: dict[str, NDArray[np.bool_]] = field(default_factory=dict)


@dataclass(frozen=True)
class DtmHeights:
    """A DTM read by windows, for the heights under objects (``yield ... deeper``):
    ``read(r0, r1, c0, c1)`` gives rows r0:r1 and columns c0:c1 of a grid of ``shape``
    cells (NaN nodata) whose geotransform is ``transform`` (north up)."""

    read: Callable[[int, int, int, int], NDArray]
    shape: tuple[int, int]
    transform: Affine

    #: cells a side of the blocks an object's heights are read in (memory follows a block)
    BLOCK = 1024

    @classmethod
    def of(cls, dtm: NDArray, transform: Affine) -> DtmHeights:
        """Heights of a DTM held as an array."""
        z = np.asarray(dtm)
        return cls(lambda r0, r1, c0, c1: z[r0:r1, c0:c1], (z.shape[0], z.shape[1]), transform)

    def window(self, bounds: tuple[float, float, float, float]) -> tuple[NDArray, Affine]:
        """The cells covering map ``bounds`` (x0, y0, x1, y1), cut at the DTM's edges, and
        their geotransform (``edges.Reader``)."""
        t = self.transform
        x0, y0, x1, y1 = bounds
        c0 = max(0, int(np.floor((x0 - t.c) / t.a + 1e-9)))
        c1 = min(self.shape[1], max(c0, int(np.ceil((x1 - t.c) / t.a - 1e-9))))
        r0 = max(0, int(np.floor((y1 - t.f) / t.e + 1e-9)))
        r1 = min(self.shape[0], max(r0, int(np.ceil((y0 - t.f) / t.e - 1e-9))))
        z = np.asarray(self.read(r0, r1, c0, c1), dtype=np.float64)
        return z, t @ Affine.translation(c0, r0)

    def within(self, geom: Any) -> NDArray[np.float64]:
        """Heights (with data) of the cells whose centres lie in ``geom``, read block by
        block over the blocks its bounds reach that it touches."""
        t = self.transform
        if geom.is_empty or t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            if not geom.is_empty:
                raise ParameterError("DTM heights need a north-up geotransform")
            return np.zeros(0)
        x0, y0, x1, y1 = geom.bounds
        c0 = max(0, int(np.floor((x0 - t.c) / t.a - 0.5)))
        c1 = min(self.shape[1], int(np.ceil((x1 - t.c) / t.a - 0.5)) + 1)
        r0 = max(0, int(np.floor((y1 - t.f) / t.e - 0.5)))
        r1 = min(self.shape[0], int(np.ceil((y0 - t.f) / t.e - 0.5)) + 1)
        out = []
        shapely.prepare(geom)
        for br in range(r0, r1, self.BLOCK):
            er = min(r1, br + self.BLOCK)
            for bc in range(c0, c1, self.BLOCK):
                ec = min(c1, bc + self.BLOCK)
                corner = t @ (bc, br)
                far = t @ (ec, er)
                if not geom.intersects(shapely.box(corner[0], far[1], far[0], corner[1])):
                    continue
                xs = t.c + (np.arange(bc, ec) + 0.5) * t.a
                ys = t.f + (np.arange(br, er) + 0.5) * t.e
                gx, gy = np.meshgrid(xs, ys)
                inside = shapely.contains_xy(geom, gx, gy)
                if inside.any():
                    z = np.asarray(self.read(br, er, bc, ec), dtype=np.float64)[inside]
                    out.append(z[np.isfinite(z)])
        return np.concatenate(out) if out else np.zeros(0)


def builtin_filter_names() -> list[str]:
    """Names of the shipped filters, in the seed's order."""
    return list(_BUILTIN)


def load_filter(name: str) -> Filter:
    """A built-in or optional shipped filter by name; unknown names raise ParameterError."""
    if name not in _BUILTIN + _OPTIONAL:
        raise ParameterError(
            f"unknown filter {name!r} (built-in: {', '.join(_BUILTIN + _OPTIONAL)})"
        )
    text = (
        resources.files(__package__).joinpath("filters", f"{name}.flt").read_text(encoding="utf-8")
    )
    return parse_filter(text, name)


def resolve_filters(spec: str = "all", user: dict[str, str] | None = None) -> list[Filter]:
    """Filters for a job's ``features`` parameter; ``user`` maps names to posted filter texts (parsed here)."""
    user = user or {}
    parsed = {name: parse_filter(text, name) for name, text in user.items()}
    spec = spec.strip()
    if spec == "none":
        return []
    names = (
        [*_BUILTIN, *parsed] if spec == "all" else [n.strip() for n in spec.split(",") if n.strip()]
    )
    return [parsed[n] if n in parsed else load_filter(n) for n in names]


def _tile_transform(cats: Categories, transform: Affine, tile_size: float) -> Affine:
    step = abs(transform.a)
    if np.isclose(step, tile_size, rtol=1e-6):
        return transform
    if np.isclose(step * cats.cells_per_tile, tile_size, rtol=1e-6):
        return cats.transform(transform)
    raise ParameterError(
        f"transform cell {step} fits neither the tile size {tile_size} nor its DTM cell"
    )


@register(
    "features",
    FeatureParams,
    "Terrain objects (ditch, ridge, hill, pond, road, flat areas) from categories",
)
def categories_for(
    dtm: NDArray,
    cell: float,
    filters: list[Filter],
    params: CategoryParams | None = None,
    origin: tuple[int, int] = (0, 0),
) -> tuple[Categories, dict[GridKey, Categories]]:
    """Categories of ``dtm`` on the tile grid and on every other grid ``filters`` ask for
    (overlapping tiles, a detrended DTM), ready for
    ``detect_features(cats, filters, ..., stepped=stepped)``; a ``diagonal`` filter's
    grid carries its turned marks (``Categories.turned``), whose lattice is fixed to
    the whole DTM's first cell: ``origin`` is ``dtm``'s first cell in the whole DTM."""
    params = params or CategoryParams()
    if params.noise is None:  # one noise for every grid: the DTM's own
        params = params.model_copy(update={"noise": measure_noise(dtm, cell, params)})
    if params.slope_noise is None:  # and one slope noise
        sigma_g = 0.0 if params.noise == 0 else measure_slope_noise(dtm, cell, params)
        params = params.model_copy(update={"slope_noise": sigma_g})
    keys = grid_keys(filters)
    others: dict[GridKey, Categories] = {}
    cats = None
    for step in sorted({k[0] for k in keys} | {None}, key=lambda v: v or 0.0):
        # the grids of one step share their plane fits (category_grids), the tile
        # grid's with the detrended grids of abutting tiles
        mine = [k for k in keys if k[0] == step]
        windows = [w for _, w in mine]
        if step is None:
            windows = [None, *windows]
        trends = [
            None if w is None else regional_gradient(dtm, cell, params, w, step) for w in windows
        ]
        made = category_grids(dtm, cell, params, step, trends)
        if step is None:
            cats, made = made[0], made[1:]
        others.update(zip(mine, made, strict=True))
    assert cats is not None
    for flt in filters:
        key = grid_key(flt)
        if flt.diagonal is not None and key is not None and key[1] is None:
            if others[key].turned is not None:
                raise ParameterError(f"filter {flt.name}: one diagonal filter per grid")
            g = others[key]
            resolved = resolve_lengths(flt, g.spacing)
            others[key] = replace(g, turned=turned_marks(dtm, cell, params, g, resolved, origin))
    return cats, others


def check_filters(filters: list[Filter], tile_size: float) -> None:
    """Raise FilterSyntaxError now if a filter's metres break a limit in tiles of ``tile_size``
    (or of its own step), so a job fails when submitted rather than when finishing."""
    for f in filters:
        resolve_lengths(f, f.step.value if f.step is not None else tile_size)


def grid_key(flt: Filter) -> GridKey | None:
    """The grid ``flt`` runs on other than the tile grid: (``step``, ``detrend``) in metres."""
    if flt.step is None and flt.detrend is None:
        return None
    return (
        None if flt.step is None else flt.step.value,
        None if flt.detrend is None else flt.detrend.value,
    )


def grid_keys(filters: list[Filter]) -> list[GridKey]:
    """The other grids the filters run on (overlapping tiles, detrended DTM), each once."""
    keys = {k for f in filters if (k := grid_key(f)) is not None}
    return sorted(keys, key=lambda k: (k[0] or 0.0, k[1] or 0.0))


def detect_features(
    categories: Categories,
    filters: list[Filter],
    transform: Affine,
    tile_size: float,
    params: FeatureParams | None = None,
    *,
    stepped: dict[GridKey, Categories] | None = None,
    dtm: NDArray | None = None,
) -> FeatureResult:
    """Run ``filters`` over the category grid.

    ``transform`` is the DTM's geotransform or the tile grid's (told apart by
    cell size); polygons come out in its CRS. Objects of all filters go to
    ``objects``; filters without connect/findrectangle mark tiles in ``marked``.
    Filters with a ``step`` or ``detrend`` run on ``stepped[grid_key(filter)]``:
    categories of overlapping tiles (``compute_categories(..., step=step)``, which
    need the DTM's transform) or of the detrended DTM (``categories_for`` makes them).
    ``dtm`` is the DTM the categories were made of, which a ``yield ... deeper`` rule
    reads the heights under objects from (required when such a rule can apply), and a
    filter's ``edges`` reads its objects' sides from.
    """
    params = params or FeatureParams()
    tt = _tile_transform(categories, transform, tile_size)
    result = FeatureResult()
    for flt in filters:
        cats, grid = categories, tt
        key = grid_key(flt)
        if key is not None:
            found = (stepped or {}).get(key)
            if found is None:
                raise ParameterError(f"filter {flt.name} runs on grid {key}: pass its categories")
            cats = found
            if found.step_cells is not None:
                if not np.isclose(abs(transform.a) * cats.cells_per_tile, cats.tile_size):
                    raise ParameterError(f"filter {flt.name} needs the DTM's transform")
                grid = cats.transform(transform)
        flt = resolve_lengths(flt, cats.spacing)
        result.objects += _run_filter(cats, flt, grid, params, result)
    heights = None
    if dtm is not None:
        k = categories.cells_per_tile
        rows, cols = np.shape(dtm)
        if not (rows // k <= categories.shape[0] <= -(-rows // k)) or not (
            cols // k <= categories.shape[1] <= -(-cols // k)
        ):
            raise ParameterError(
                f"dtm of {rows}x{cols} cells does not match {categories.shape[0]}x"
                f"{categories.shape[1]} category tiles of {k} cells"
            )
        # ``transform`` is the tile grid's when it is the grid's own (``_tile_transform``)
        dtm_transform = transform @ Affine.scale(1 / k) if tt is transform else transform
        heights = DtmHeights.of(dtm, dtm_transform)
    result.objects = apply_yields(
        result.objects, filters, categories.tile_size, heights, categories.noise
    )
    return result


def apply_yields(
    objects: list[Feature],
    filters: list[Filter],
    tile_size: float,
    heights: DtmHeights | None = None,
    noise: float | None = None,
) -> list[Feature]:
    """``objects`` without those a filter's ``edges`` (with ``heights``, the DTM) or
    ``bank`` drops, split where its ``split`` cuts them (``_split_across``), and then
    without those its ``yield`` drops: an object with at least the
    share of its area within the distance (tiles of ``tile_size`` metres, or metres) of an
    object of the named filter, as that filter found it, or, where the rule gives a length,
    no part of it beyond the distance that long. A named filter that did not run takes
    nothing away. Where the rule says ``deeper k``, the object yields only if its median
    height in ``heights`` (the DTM) is not more than k × ``noise`` (the DTM's noise σ, as
    the flatness tests take it) below the median height of the named filter's objects
    alongside it (their parts within the distance plus their own width of it); without
    ``heights`` such a rule raises ParameterError when the named filter is among
    ``filters`` (or objects of it are given)."""
    ran = {f.name for f in filters} | {o.kind for o in objects}
    deeper = {f.name: dict(f.yield_deeper) for f in filters if f.yield_deeper}
    needs = [f"{k} (yield {o} deeper)" for k, d in deeper.items() for o in d if o in ran]
    if needs and (heights is None or noise is None):
        raise ParameterError(
            f"filter {', '.join(needs)} compares heights: pass the DTM"
            + (" and its noise" if heights is not None else "")
        )
    rules = {f.name: f.yields for f in filters if f.yields}
    # an object is measured on its filter's grid: overlapping tiles laid every step
    grid = {f.name: tile_size if f.step is None else f.step.value for f in filters}
    if heights is not None:
        objects = _drop_unbounded(objects, filters, tile_size, heights)
    banks = _banks(objects, filters)
    objects = [o for i, o in enumerate(objects) if i not in banks]
    objects = _split_across(objects, filters, grid)
    if not rules:
        return objects
    by_kind: dict[str, list[Feature]] = {}
    for o in objects:
        by_kind.setdefault(o.kind, []).append(o)
    drop: set[int] = set()
    for kind, yields in rules.items():
        mine = [i for i, o in enumerate(objects) if o.kind == kind]
        for other, reach, share, *rest in yields:
            theirs = by_kind.get(other)
            if not theirs or not mine:
                continue
            d = reach.value if isinstance(reach, Metres) else reach * tile_size
            zone = shapely.union_all([o.geometry for o in theirs]).buffer(d)
            k = deeper.get(kind, {}).get(other)
            for i in mine:
                g = objects[i].geometry
                inside = g.intersection(zone).area if g.area > 0 else 0.0
                if (
                    inside > 0
                    and (
                        inside >= share * g.area
                        or _short_rest(g, zone, rest, tile_size, grid[kind])
                    )
                    and (k is None or not _deeper(g, theirs, d, k * (noise or 0.0), heights))
                ):
                    drop.add(i)
    return [o for i, o in enumerate(objects) if i not in drop]


def _deeper(
    geom: Polygon | MultiPolygon,
    theirs: list[Feature],
    reach: float,
    margin: float,
    heights: DtmHeights | None,
) -> bool:
    """Whether the median DTM height under ``geom`` lies more than ``margin`` below the
    median height of ``theirs`` alongside it: each one's part within ``reach`` plus its
    own width of ``geom`` (so across its whole width beside ``geom``). False where either
    has no heights."""
    assert heights is not None
    own = heights.within(geom)
    if own.size == 0:
        return False
    near = [
        o.geometry.intersection(geom.buffer(reach + o.width_m))
        for o in theirs
        if o.geometry.distance(geom) <= reach
    ]
    beside = heights.within(shapely.union_all(near)) if near else np.zeros(0)
    if beside.size == 0:
        return False
    return float(np.median(beside)) - float(np.median(own)) > margin


def _drop_unbounded(
    objects: list[Feature], filters: list[Filter], tile_size: float, heights: DtmHeights
) -> list[Feature]:
    """``objects`` without the troughs, verges and slope bands of the filters with
    ``edges``."""
    drop: set[int] = set()
    for f in filters:
        if f.edges is None:
            continue
        mine = [i for i, o in enumerate(objects) if o.kind == f.name]
        for i in mine:
            others = [objects[j].geometry for j in mine if j != i]
            s = edge_sides(objects[i].geometry, heights.window, tile_size, f.edges, others)
            if s is not None and unbounded(s, f.edges, f.edges_tilt) is not None:
                drop.add(i)
    return [o for i, o in enumerate(objects) if i not in drop]


def _banks(objects: list[Feature], filters: list[Filter]) -> set[int]:
    """Indices of the objects a filter's ``bank <filter>`` drops: at least half the
    object's area lies within an object of the named filter, and that object's part
    along the object's length has its centre more than half the object's width off the
    object's long axis (its middle lies beside the object's strip, not under it)."""
    drop: set[int] = set()
    for f in filters:
        for other in f.banks:
            theirs = [o.geometry for o in objects if o.kind == other]
            if not theirs:
                continue
            for i, o in enumerate(objects):
                if o.kind == f.name and any(_on_flank(o, g) for g in theirs):
                    drop.add(i)
    return drop


def _split_across(
    objects: list[Feature], filters: list[Filter], grid: dict[str, float]
) -> list[Feature]:
    """``objects`` with each object of a filter with ``split <other>`` that lies across
    objects of ``other`` replaced by its parts off them, where those parts, joined and
    measured as the filter's pieces are on its grid of ``grid`` metres (``finish_pieces``
    with its resolved ``join`` and connect limits), make two objects or more. Each part
    keeps the object's tiles in proportion to its area."""
    out = list(objects)
    for f in filters:
        if not f.splits or f.connect is None:
            continue
        cut = [o.geometry for o in out if o.kind in f.splits]
        if not cut:
            continue
        zone = shapely.union_all(cut)
        shapely.prepare(zone)
        spacing = grid[f.name]
        opts = object_options(resolve_lengths(f, spacing), FeatureParams())
        limits = opts.pop("limits")
        opts.pop("fill_holes", None)
        opts.pop("simplify_tiles", None)
        mine: list[Feature] = []
        for o in out:
            g = o.geometry
            if o.kind != f.name or g.area <= 0 or not zone.intersects(g):
                mine.append(o)
                continue
            parts = [
                p
                for p in shapely.get_parts(g.difference(zone))
                if isinstance(p, Polygon) and p.area > 0
            ]
            pieces = []
            for p in parts:
                length, width = rectangle_size(p)
                share = round(o.tiles * p.area / g.area)
                pieces.append(Feature(o.kind, p, float(length), float(width), share))
            split = finish_pieces(pieces, spacing, limits, **opts) if len(pieces) > 1 else []
            mine += split if len(split) > 1 else [o]
        out = mine
    return out


def _on_flank(o: Feature, g: Polygon | MultiPolygon) -> bool:
    """Whether ``o`` lies on the flank of ``g`` (see ``_banks``)."""
    own = o.geometry
    if own.area <= 0 or own.intersection(g).area < 0.5 * own.area:
        return False
    xy = np.asarray(own.minimum_rotated_rectangle.exterior.coords)[:4]
    sides = [xy[1] - xy[0], xy[2] - xy[1]]
    along = max(sides, key=lambda v: float(np.hypot(*v)))
    half_len = float(np.hypot(*along)) / 2
    u = along / (2 * half_len)
    n = np.array([-u[1], u[0]])
    mid = xy.mean(axis=0)
    x0, y0, x1, y1 = g.bounds
    reach = max(float(np.hypot(x - mid[0], y - mid[1])) for x in (x0, x1) for y in (y0, y1))
    band = Polygon(
        [
            mid - half_len * u - reach * n,
            mid + half_len * u - reach * n,
            mid + half_len * u + reach * n,
            mid - half_len * u + reach * n,
        ]
    )
    part = g.intersection(band)
    if part.area <= 0:
        return False
    centre = np.asarray(own.centroid.coords[0])
    off = abs(float(np.dot(np.asarray(part.centroid.coords[0]) - centre, n)))
    return off > o.width_m / 2


def _short_rest(
    geom: Polygon | MultiPolygon, zone: Any, rest: list[Length], tile_size: float, grid: float
) -> bool:
    """No part of ``geom`` outside ``zone`` is as long as ``rest[0]`` (tiles of ``tile_size``
    metres, or metres), each part measured as ``finish_pieces`` measures an object on a
    grid of ``grid`` metres; False without a length."""
    if not rest:
        return False
    r = rest[0]
    least = r.value if isinstance(r, Metres) else r * tile_size
    parts = shapely.get_parts(geom.difference(zone))
    return not any(
        isinstance(p, Polygon) and p.area > 0 and _measured(p, grid)[0] >= least for p in parts
    )


def _run_filter(
    categories: Categories,
    flt: Filter,
    tt: Affine,
    params: FeatureParams,
    result: FeatureResult,
) -> list[Feature]:
    """Objects of one resolved filter (marks of a filter with no object step go to ``result``)."""
    labels, marks, _ = filter_labels(categories, flt)
    if labels is None:
        result.marked[flt.name] = marks
        return []
    return objects_from_labels(
        labels, flt.name, tt, categories.spacing, **object_options(flt, params)
    )


def filter_labels(
    categories: Categories, flt: Filter, whole: bool = True
) -> tuple[NDArray[np.int32] | None, NDArray[np.bool_], NDArray[np.bool_]]:
    """A resolved filter's object labels (None without a connect or rectangle step),
    its marked tiles, and the tiles its objects are grown from (marks found either
    way; a rectangle's cover): every object lies within that support and depends
    only on the part of it that it touches. ``whole=False`` leaves out the rules that
    judge a label as a whole (``whole_label_rules``), for a window that holds only
    part of some labels."""
    h, v = search_filter(categories, flt)
    support = h | v
    if flt.h_and_v:
        marks = _connect.h_and_v(h, v, flt.h_and_v_share)
        h, v = h & marks, v & marks
    else:
        marks = h | v
    if flt.rectangle is not None:
        if flt.majority:
            marks = majority_marks(marks, categories)
        r = flt.rectangle
        cover = _connect.rectangle_cover(marks, r.width, r.height, r.error)
        labels, _ = ndimage.label(cover)  # one object per connected cover: its marked tiles
        labels[~marks] = 0
        # an object is a connected cover's marked tiles, and whether a tile is covered
        # follows from the marks within one rectangle of it: marks outside the cover
        # join nothing, so the cover alone is the support (scattered marks on open
        # terrain would otherwise join into one support across the whole DTM)
        return labels.astype(np.int32), marks, cover
    if flt.connect is None:
        return None, marks, support
    c = flt.connect
    if c.method == "simple":
        labels = _connect.simple(marks)
    elif c.method == "segment":
        gap = int(c.max_error // 10)  # runs of missing lines bridged: 2 at 20 %
        labels = _connect.segments(h, v, gap)
    else:
        labels = _connect.edges(categories, h, v, marks)
    if whole:
        labels = whole_label_rules(labels, categories, flt, support)
    return labels, marks, support


def majority_marks(marks: NDArray[np.bool_], categories: Categories) -> NDArray[np.bool_]:
    """``marks`` with every unmarked tile that is not ``clear`` marked where more than half
    of the tiles with data among it and its 8 neighbours are marked (``majority``). On a
    plane just under the flatness threshold each tile's fitted slope carries the DTM's
    slope noise and tips past the threshold at random; a tile not clearly past it is read
    again from its neighbours on the same plane (tiles tipped independently with chance
    0.19, the share seen near the threshold on a 3 points/m^2 job DTM, stay tipped where
    4 of their 8 neighbours are tipped too: 0.9 % of the tiles, under a square's 5 %). A
    tile clearly past the threshold stays as it reads."""
    clear = categories.clear
    if clear is None:  # without the band every tile that is not flat counts as clear
        return marks
    valid = categories.inclination != NODATA
    ones = np.ones((3, 3), np.int32)
    marked = ndimage.convolve(marks.astype(np.int32), ones, mode="constant")
    around = ndimage.convolve(valid.astype(np.int32), ones, mode="constant")
    return marks | (valid & (clear == 0) & (2 * marked > around))


def whole_label_rules(
    labels: NDArray[np.int32],
    categories: Categories,
    flt: Filter,
    support: NDArray[np.bool_] | None = None,
) -> NDArray[np.int32]:
    """Labels without those a rule over the whole label drops: a segment-connected
    object missing too many lines (``connect segment``'s error), one not clear
    enough (``clear-share``), one on ground as busy as itself (``surround``, which
    needs the filter's ``support``), one not enclosed by rising ground (``enclosed``), one
    that runs on into inclined ground around it (``isolated``)."""
    c = flt.connect
    if flt.rectangle is not None or c is None:
        return labels
    if c.method == "segment":
        labels = _drop_gappy(labels, c.max_error)
    if flt.clear_share is not None:
        labels = _drop_unclear(
            labels, categories, flt.clear_share, clear_exempt_tiles(flt, categories)
        )
    if flt.surround is not None:
        if support is None:
            raise ParameterError(f"filter {flt.name}: surround needs the filter's support")
        labels = _drop_busy(labels, categories, support, *flt.surround)
    if flt.enclosed is not None:
        labels = _drop_open(labels, categories, *flt.enclosed)
    if flt.isolated is not None:
        labels = _drop_continued(labels, categories, *flt.isolated)
    return labels


Rim = tuple[frozenset[tuple[int, int, int]], float, float, int]
"""Around a label (or a part of it): the inclined tiles within the distance (with
``every``, all tiles with data, 0 for flat ones), as (row, column, inclination) over the
whole grid, and the sums of its tiles' rows and columns and their count (its centre),
which add up over the parts of a label."""


def rim_sets(
    labels: NDArray[np.int32],
    found: list[int],
    categories: Categories,
    distance: int,
    origin: tuple[int, int] = (0, 0),
    every: bool = False,
) -> dict[int, Rim]:
    """Per label in ``found``: its ``Rim`` within ``distance`` tiles (its holes filled,
    the tiles outside it); ``every`` keeps the flat tiles too. ``origin`` offsets a
    window's rows and columns."""
    inc = categories.inclination
    inclined = (inc != NODATA) if every else (inc > 0) & (inc != NODATA)
    g0, c0 = origin
    d = 2 * distance + 1
    boxes = ndimage.find_objects(labels)
    out: dict[int, Rim] = {}
    for lab in found:
        box = boxes[lab - 1] if lab <= len(boxes) else None
        if box is None:
            out[lab] = (frozenset(), 0.0, 0.0, 0)
            continue
        r0, r1 = max(0, box[0].start - distance), min(labels.shape[0], box[0].stop + distance)
        b0, b1 = max(0, box[1].start - distance), min(labels.shape[1], box[1].stop + distance)
        mine = ndimage.binary_fill_holes(labels[r0:r1, b0:b1] == lab)
        ring = square_dilation(mine, d) & ~mine
        a, b = np.nonzero(ring & inclined[r0:r1, b0:b1])
        tiles = frozenset(
            zip(
                (g0 + r0 + a).tolist(),
                (c0 + b0 + b).tolist(),
                inc[r0:r1, b0:b1][a, b].tolist(),
                strict=True,
            )
        )
        rr, cc = np.nonzero(labels[r0:r1, b0:b1] == lab)
        out[lab] = (tiles, float((g0 + r0 + rr).sum()), float((c0 + b0 + cc).sum()), rr.size)
    return out


def rim_sectors(rim: Rim) -> int:
    """Bearing sectors (of 8, from the centre) holding a tile of the rim that rises away
    from the centre: its inclination within 45° of the tile's bearing."""
    tiles, sum_r, sum_c, n = rim
    if n == 0 or not tiles:
        return 0
    t = np.array(sorted(tiles), dtype=float)
    t = t[t[:, 2] > 0]
    bearing = np.arctan2(-(t[:, 0] - sum_r / n), t[:, 1] - sum_c / n)  # rows run south
    rising = (t[:, 2] - 1) * np.pi / 4  # 1 east, 3 north, counter-clockwise
    away = np.abs((rising - bearing + np.pi) % (2 * np.pi) - np.pi) <= np.pi / 4 + 1e-9
    sector = np.floor(((bearing[away] + np.pi / 8) % (2 * np.pi)) / (np.pi / 4)).astype(int)
    return int(np.unique(sector % 8).size)


def rim_leak(rim: Rim) -> float:
    """Share of a rim's tiles (one made with ``every``) that are inclined other than rising
    toward the centre (their inclination more than 45° from the bearing to it): ground
    that runs on past the object rather than falling to its foot."""
    tiles, sum_r, sum_c, n = rim
    if n == 0 or not tiles:
        return 0.0
    t = np.array(sorted(tiles), dtype=float)
    bearing = np.arctan2(-(t[:, 0] - sum_r / n), t[:, 1] - sum_c / n)  # centre -> tile
    rising = (t[:, 2] - 1) * np.pi / 4
    toward = np.abs((rising - bearing) % (2 * np.pi) - np.pi) <= np.pi / 4 + 1e-9
    leak = (t[:, 2] > 0) & ~toward
    return float(leak.mean())


def _drop_open(
    labels: NDArray[np.int32], categories: Categories, distance: int, sectors: int
) -> NDArray[np.int32]:
    """Remove objects whose rim (``rim_sets``) rises away from them in fewer than
    ``sectors`` of the 8 bearing sectors (``enclosed``); reads tiles within ``distance``
    of the object only (``connect_reach`` grows its closure by as much)."""
    n = int(labels.max())
    if n == 0:
        return labels
    rims = rim_sets(labels, list(range(1, n + 1)), categories, distance)
    keep = np.zeros(n + 1, dtype=bool)
    for lab, rim in rims.items():
        keep[lab] = rim[3] > 0 and rim_sectors(rim) >= sectors
    return np.where(keep[labels], labels, 0).astype(np.int32)


def _drop_continued(
    labels: NDArray[np.int32], categories: Categories, distance: int, share: float
) -> NDArray[np.int32]:
    """Remove objects whose rim (``rim_sets`` with every tile) holds more than ``share``
    of tiles inclined other than rising toward them (``rim_leak``; ``isolated``); reads
    tiles within ``distance`` of the object only (``connect_reach`` grows its closure)."""
    n = int(labels.max())
    if n == 0:
        return labels
    rims = rim_sets(labels, list(range(1, n + 1)), categories, distance, every=True)
    keep = np.zeros(n + 1, dtype=bool)
    for lab, rim in rims.items():
        keep[lab] = rim[3] > 0 and rim_leak(rim) <= share
    return np.where(keep[labels], labels, 0).astype(np.int32)


def connect_reach(flt: Filter) -> int:
    """Tiles across which ``filter_labels`` joins two marked tiles into one object, or
    around an object within which it reads the categories (``surround``): an object
    depends on its support grown by this much (a resolved filter)."""
    if flt.rectangle is not None or flt.connect is None:
        return 1
    if flt.connect.method == "segment":
        reach = int(flt.connect.max_error // 10) + 1
    else:
        reach = 2 if flt.connect.method == "edge" else 1
    if flt.surround is not None:
        reach = max(reach, int(flt.surround[0]))
    if flt.enclosed is not None:
        reach = max(reach, int(flt.enclosed[0]))
    if flt.isolated is not None:
        reach = max(reach, int(flt.isolated[0]))
    return reach


def object_options(flt: Filter, params: FeatureParams) -> dict[str, Any]:
    """``objects_from_labels`` keywords of a resolved filter with an object step."""
    if flt.rectangle is not None:
        return {
            "simplify_tiles": params.simplify_tiles,
            "fill_holes": False,
            "measure": "rectangle",
        }
    c = flt.connect
    assert c is not None
    return {
        "limits": (c.min_length, c.max_length, c.min_width, c.max_width),
        "simplify_tiles": params.simplify_tiles,
        "aspect": (flt.aspect.min, flt.aspect.max) if flt.aspect else (None, None),
        "join": flt.join,
        "join_aligned": flt.join_aligned,
        "hull": flt.hull,
        "solidity": flt.solidity,
        "join_line": flt.join_line,
    }


def clear_exempt_tiles(flt: Filter, categories: Categories) -> float | None:
    """Tiles from which a resolved filter's object needs no clear share (``clear-share``'s
    noise multiple: as many as the connect step's smallest length, where the DTM's slope
    noise cannot tip a level tile past the flatness threshold), or None."""
    c = flt.connect
    if flt.clear_exempt is None or c is None or categories.flat_sigmas < flt.clear_exempt:
        return None
    return float(c.min_length or 1)


def clear_kept(
    counted: NDArray | float,
    clear: NDArray | float,
    tiles: NDArray | float,
    share: float,
    exempt: float | None,
) -> NDArray[np.bool_]:
    """Which objects ``clear-share`` keeps, from ``clear_counts``' sums."""
    keep = np.asarray(clear) >= share * np.asarray(counted)
    if exempt is not None:
        keep |= np.asarray(tiles) >= exempt
    return keep


def _drop_unclear(
    labels: NDArray[np.int32], categories: Categories, share: float, exempt: float | None = None
) -> NDArray[np.int32]:
    """Remove objects whose tiles that are not flat are clearly not flat (``Categories.clear``)
    for less than ``share`` of them, unless they have ``exempt`` tiles or more. Each object
    is a whole connected label, so the test is the same wherever a window cuts the DTM
    (``tiled``). Without the band every tile that is not flat counts as clear."""
    n = int(labels.max())
    if n == 0 or categories.clear is None:
        return labels
    counted, clear, tiles = clear_counts(labels, categories, n)
    keep = np.zeros(n + 1, dtype=bool)
    keep[1:] = clear_kept(counted, clear, tiles, share, exempt)
    return np.where(keep[labels], labels, 0).astype(np.int32)


def clear_counts(
    labels: NDArray[np.int32], categories: Categories, n: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per label 1..n: its tiles that are not flat, of those the clearly not flat ones,
    and all its tiles (``_drop_unclear``'s sums, which add up over the parts of a label)."""
    assert categories.clear is not None
    inc, ori, st = categories.inclination, categories.orientation, categories.state
    not_flat = ((inc | ori | st) != 0) & (inc != NODATA)
    idx = np.arange(1, n + 1)
    counted = ndimage.sum_labels(not_flat, labels, idx)
    clear = ndimage.sum_labels(not_flat & (categories.clear == 1), labels, idx)
    tiles = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    return np.asarray(counted, float), np.asarray(clear, float), np.asarray(tiles, float)


def _drop_busy(
    labels: NDArray[np.int32],
    categories: Categories,
    support: NDArray[np.bool_],
    distance: int,
    share: float,
) -> NDArray[np.int32]:
    """Remove objects around which, within ``distance`` tiles, more than ``share`` of the
    tiles with data that the filter does not mark (``support``) are not flat. Reads only
    tiles within ``distance`` of the object (``connect_reach`` grows its closure by as
    much), so the test is the same wherever a window cuts the DTM (``tiled``)."""
    n = int(labels.max())
    if n == 0:
        return labels
    inc, ori, st = categories.inclination, categories.orientation, categories.state
    valid = inc != NODATA
    open_ground = valid & ~support
    not_flat = open_ground & ((inc | ori | st) != 0)
    d = 2 * distance + 1
    keep = np.zeros(n + 1, dtype=bool)
    for lab, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        # the object's box grown by the distance, clipped to the grid
        r0, r1 = max(0, box[0].start - distance), min(labels.shape[0], box[0].stop + distance)
        c0, c1 = max(0, box[1].start - distance), min(labels.shape[1], box[1].stop + distance)
        ring = square_dilation(labels[r0:r1, c0:c1] == lab, d)
        around = int((ring & open_ground[r0:r1, c0:c1]).sum())
        busy = int((ring & not_flat[r0:r1, c0:c1]).sum())
        keep[lab] = busy <= share * around
    return np.where(keep[labels], labels, 0).astype(np.int32)


def _drop_gappy(labels: NDArray[np.int32], max_error: float) -> NDArray[np.int32]:
    """Remove segment-connected objects missing more than ``max_error`` % of the lines along their long axis."""
    n = int(labels.max())
    if n == 0:
        return labels
    keep = np.zeros(n + 1, dtype=bool)
    for lab_id, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        sub = labels[box] == lab_id
        rows, cols = sub.any(axis=1), sub.any(axis=0)
        present, span = (
            (rows.sum(), rows.size) if rows.size >= cols.size else (cols.sum(), cols.size)
        )
        keep[lab_id] = (span - present) <= max_error / 100 * span
    return np.where(keep[labels], labels, 0).astype(np.int32)


def _round_mm(xy: NDArray) -> NDArray:
    return np.round(xy, 3)


def features_geojson(
    result: FeatureResult, crs_wkt_or_epsg: str | int, job_id: str | None, to_wgs84: bool
) -> dict:
    """RFC 7946 FeatureCollection of ``result.objects``: lon/lat WGS 84 when ``to_wgs84``, else native coordinates."""
    project = None
    if to_wgs84:
        from pyproj import CRS, Transformer

        src = CRS.from_user_input(crs_wkt_or_epsg)
        tr = Transformer.from_crs(src, CRS.from_epsg(4326), always_xy=True)

        def project(xy: NDArray) -> NDArray:
            return np.round(np.column_stack(tr.transform(xy[:, 0], xy[:, 1])), 7)  # ~1 cm

    feats = []
    for i, f in enumerate(result.objects):
        geom = orient(f.geometry, 1.0) if f.geometry.geom_type == "Polygon" else f.geometry
        geom = (
            shapely.transform(geom, project)
            if project is not None
            else shapely.transform(geom, _round_mm)
        )
        props = {
            "kind": f.kind,
            "length_m": round(f.length_m, 2),
            "width_m": round(f.width_m, 2),
            "tiles": f.tiles,
        }
        if job_id is not None:
            props["job_id"] = job_id
        feats.append(
            {"type": "Feature", "id": i + 1, "geometry": mapping(geom), "properties": props}
        )
    return {"type": "FeatureCollection", "features": feats}
