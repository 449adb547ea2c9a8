"""Objects out: labelled tiles → shapely polygons with length and width in metres.

An object's polygon is the union of its tiles (holes it encloses filled, since
e.g. a hill is found by its outline; pieces an edge or segment connect joined
across a missing line closed into one outline), simplified by half a tile.

Length and width keep the seed's idea (width across, length = area / width)
but do not depend on the object's angle to the rows: the seed's mean
row-segment width overstates the width of a diagonal object by 1/cos of its
angle and so understates its length by as much (§5.3.2 notes the width is
inexact). The outline is first smoothed by a morphological closing and opening
of 0.75 tile (a tile staircase is up to √2 too long). An elongated object
takes the rectangle with the outline's area and perimeter (L + W = P/2,
L·W = A), which follows bends; a compact one (that rectangle's aspect below
3, where the solution is ill-conditioned) the axes of the ellipse with the
outline's second moments, so a round hill's length is its diameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from rasterio import Affine
from rasterio.features import rasterize, shapes
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from shapely.geometry import LinearRing, LineString, MultiPolygon, Polygon, shape
from shapely.ops import nearest_points, unary_union


@dataclass(frozen=True)
class Feature:
    """One terrain object."""

    kind: str
    geometry: Polygon | MultiPolygon
    length_m: float
    width_m: float
    tiles: int


def square_dilation(mask: NDArray[np.bool_], d: int) -> NDArray[np.bool_]:
    """``ndimage.binary_dilation(mask, np.ones((d, d), bool))`` for odd ``d``: a square
    grows as a row then a column (cells beyond the array are empty), each a running
    maximum, so the cost does not grow with the square's area."""
    grown = ndimage.maximum_filter1d(mask.view(np.uint8), d, axis=1, mode="constant", cval=0)
    return ndimage.maximum_filter1d(grown, d, axis=0, mode="constant", cval=0) > 0


def fill_object_holes(labels: NDArray[np.int32]) -> NDArray[np.int32]:
    """Label image with every enclosed hole given to an object bordering it."""
    mask = labels > 0
    holes = ndimage.binary_fill_holes(mask) & ~mask
    if not holes.any():
        return labels
    hole_lab, n = ndimage.label(holes)
    around = ndimage.grey_dilation(labels, footprint=ndimage.generate_binary_structure(2, 1))
    owner = ndimage.maximum(around, hole_lab, index=np.arange(1, n + 1)).astype(np.int32)
    out = labels.copy()
    out[holes] = owner[hole_lab[holes] - 1]
    return out


def moment_size(poly: Polygon | MultiPolygon) -> tuple[float, float]:
    """Axes of the ellipse with the second area moments of ``poly`` (4√λ1, 4√λ2): a disc's diameter."""
    parts = poly.geoms if isinstance(poly, MultiPolygon) else [poly]
    area = sxx = syy = sxy = 0.0
    cx, cy = poly.centroid.x, poly.centroid.y
    for p in parts:
        xy = np.asarray(p.exterior.coords) - (cx, cy)
        x0, y0, x1, y1 = xy[:-1, 0], xy[:-1, 1], xy[1:, 0], xy[1:, 1]
        cr = x0 * y1 - x1 * y0
        area += cr.sum() / 2
        sxx += (cr * (y0 * y0 + y0 * y1 + y1 * y1)).sum() / 12  # ∫ y²
        syy += (cr * (x0 * x0 + x0 * x1 + x1 * x1)).sum() / 12  # ∫ x²
        sxy += (cr * (x0 * y1 + 2 * x0 * y0 + 2 * x1 * y1 + x1 * y0)).sum() / 24
    if area == 0:
        return 0.0, 0.0
    cov = (
        np.array([[syy, sxy], [sxy, sxx]]) / area
    )  # signed sums over signed area: orientation-free
    lam = np.sort(np.linalg.eigvalsh(cov))[::-1]
    return float(4 * np.sqrt(max(lam[0], 0))), float(4 * np.sqrt(max(lam[1], 0)))


def object_size(poly: Polygon | MultiPolygon) -> tuple[float, float]:
    """(length, width): the equal area-and-perimeter rectangle for elongated
    objects (it follows bends), the equal-moments ellipse for compact ones
    (aspect < 3: hills, ponds), where the perimeter-based solution is ill-conditioned."""
    length, width = rectangle_size(poly)
    if length < 3 * width:
        return moment_size(poly)
    return length, width


def rectangle_size(poly: Polygon | MultiPolygon) -> tuple[float, float]:
    """(length, width) of the rectangle with the area and outer perimeter of ``poly``."""
    parts = poly.geoms if isinstance(poly, MultiPolygon) else [poly]
    area = sum(Polygon(p.exterior).area for p in parts)
    perim = sum(p.exterior.length for p in parts)
    disc = perim * perim / 4 - 4 * area
    width = (perim / 2 - np.sqrt(disc)) / 2 if disc > 0 else np.sqrt(area)
    width = max(width, 1e-9)
    return area / width, width


def path_length(poly: Polygon | MultiPolygon, res: float) -> float:
    """The longest path inside ``poly`` (its geodesic diameter) in metres, on a raster of
    ``res`` metres: two sweeps of shortest paths through the 8-connected cells it
    touches, from any cell to the farthest one, then from there to the farthest again.

    It follows bends, as an object's length should, but unlike area and perimeter it
    is not lengthened by a ragged or branching outline: a zigzag of short strips is
    as long as the way through it. Parts of a multipolygon (pieces joined across
    gaps) are linked by the shortest tree of straight bridges and measured as one."""
    if isinstance(poly, MultiPolygon):
        # the way through pieces joined across gaps crosses the gaps: link the parts by
        # the shortest tree of straight bridges (Prim's) and measure the whole
        parts = list(poly.geoms)
        linked, rest, bridges = [parts[0]], parts[1:], []
        while rest:
            j, q = min(
                ((i, q) for i in range(len(rest)) for q in linked),
                key=lambda t: t[1].distance(rest[t[0]]),
            )
            a, b = nearest_points(q, rest[j])
            bridges.append(LineString([a, b]).buffer(0.75 * res, cap_style="square"))
            linked.append(rest.pop(j))
        whole = unary_union([poly, *bridges])
        if isinstance(whole, MultiPolygon):  # not expected: add the parts up
            return float(sum(path_length(p, res) for p in whole.geoms))
        return path_length(whole, res)
    x0, y0, x1, y1 = poly.bounds
    shape_ = (int(np.ceil((y1 - y0) / res)) + 2, int(np.ceil((x1 - x0) / res)) + 2)
    inside = rasterize(  # every cell touched, so a strip one cell wide stays connected
        [poly],
        out_shape=shape_,
        transform=Affine(res, 0, x0 - res, 0, -res, y1 + res),
        all_touched=True,
    ).astype(bool)
    n = int(inside.sum())
    if n < 2:
        return float(n * res)
    idx = np.full(shape_, -1, dtype=np.int64)
    idx[inside] = np.arange(n)
    h, w = shape_
    src, dst, cost = [], [], []
    for dr, dc, d in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, np.sqrt(2)), (1, -1, np.sqrt(2))):
        a = idx[: h - dr, max(0, -dc) : w - max(0, dc)]
        b = idx[dr:, max(0, dc) : w - max(0, -dc)]
        ok = (a >= 0) & (b >= 0)
        src.append(a[ok])
        dst.append(b[ok])
        cost.append(np.full(int(ok.sum()), d))
    graph = coo_matrix(
        (np.concatenate(cost), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)
    ).tocsr()
    far = dijkstra(graph, directed=False, indices=0)
    far[~np.isfinite(far)] = -1
    far = dijkstra(graph, directed=False, indices=int(np.argmax(far)))
    far[~np.isfinite(far)] = -1
    return float(far.max() * res)


def closed_across(poly: Polygon | MultiPolygon, width: float) -> Polygon | MultiPolygon:
    """``poly`` closed (grown and shrunk) by half of ``width`` metres: gaps narrower than
    the object between its parts, or between a part and a strip running beside it,
    filled, so measuring along it does not walk out and back along the strip. Bends of
    a radius over half the width and the ends are kept."""
    r = 0.5 * width
    if r <= 0:
        return poly
    closed = poly.buffer(r, quad_segs=3).buffer(-r, quad_segs=3)
    return poly if closed.is_empty else closed


def _smoothed(poly: Polygon | MultiPolygon, tile_size: float) -> Polygon | MultiPolygon:
    """The outline closed and opened by 0.75 tile, for measuring.

    A tile outline is a staircase (a 45° one is √2 too long) and ragged where
    marks fray; measuring its perimeter as is makes compact objects look long.
    Objects too thin to survive the opening are measured simplified instead.
    """
    t = 0.75 * tile_size
    smooth = poly.buffer(t, quad_segs=3).buffer(-2 * t, quad_segs=3).buffer(t, quad_segs=3)
    if smooth.is_empty or smooth.area < 0.5 * poly.area:
        return poly.simplify(t, preserve_topology=True)
    return smooth


def polygons(
    labels: NDArray[np.int32], transform: Affine, simplify: float
) -> dict[int, Polygon | MultiPolygon]:
    """Polygon per label (union of its tiles), corners merged, simplified by ``simplify`` metres."""
    pieces: dict[int, list] = {}
    for geom, value in shapes(labels, mask=labels > 0, transform=transform, connectivity=8):
        pieces.setdefault(int(value), []).append(shape(geom))
    tile = abs(transform.a)
    out = {}
    for lab, parts in pieces.items():
        g = unary_union(parts)
        if isinstance(g, MultiPolygon):  # tiles touching at corners only
            g = g.buffer(tile * 1e-3, join_style="mitre").buffer(-tile * 1e-3, join_style="mitre")
        if isinstance(g, MultiPolygon):  # pieces joined across bridged gaps (≤ 2 tiles)
            g = g.buffer(tile, join_style="mitre").buffer(-tile, join_style="mitre")
        g = scan_order(g, transform.e > 0)
        if simplify > 0:
            g = g.simplify(simplify, preserve_topology=True)
        out[lab] = g
    return out


def _ring(coords: list, rows_down: bool, outer: bool) -> list:
    """A closed ring from its top-left vertex (the first tile's corner in scan order),
    turning as ``rasterio.features.shapes`` traces an outline (holes the other way)."""
    pts = coords[:-1]
    sign = 1 if rows_down else -1
    start = min(range(len(pts)), key=lambda i: (sign * pts[i][1], pts[i][0]))
    pts = pts[start:] + pts[:start]
    if LinearRing(pts).is_ccw != (outer != rows_down):
        pts = [pts[0], *pts[:0:-1]]
    return [*pts, pts[0]]


def scan_order(geom: Polygon | MultiPolygon, rows_down: bool) -> Polygon | MultiPolygon:
    """``geom`` with every ring starting at its top-left vertex and turning one way
    (``rows_down``: y grows downwards, as tile indices do). Simplification keeps a
    ring's first vertex, so an outline made by a union (whose rings start anywhere)
    or joined from parts is simplified alike however it was made."""
    parts = geom.geoms if isinstance(geom, MultiPolygon) else [geom]
    out = [
        Polygon(
            _ring(list(p.exterior.coords), rows_down, True),
            [_ring(list(h.coords), rows_down, False) for h in p.interiors],
        )
        for p in parts
    ]
    return out[0] if len(out) == 1 else MultiPolygon(out)


def objects_from_labels(
    labels: NDArray[np.int32],
    kind: str,
    transform: Affine,
    tile_size: float,
    limits: tuple[float | None, float | None, float | None, float | None] = (
        None,
        None,
        None,
        None,
    ),
    simplify_tiles: float = 0.5,
    *,
    fill_holes: bool = True,
    measure: str = "auto",
    aspect: tuple[float | None, float | None] = (None, None),
    join: float | str | None = None,
    join_aligned: float | None = None,
    hull: bool = False,
    solidity: float | None = None,
    join_line: float | None = None,
) -> list[Feature]:
    """Features for every label whose length/width (in tiles) lie within ``limits``.

    ``fill_holes`` gives enclosed holes to the object (an outline found by its
    flanks); ``measure`` ``rectangle`` sizes every object by the rectangle with
    its second area moments (areas made of rectangular windows), ``auto`` as
    ``object_size``. ``aspect`` bounds length / width; ``join`` (tiles, or
    ``"width"``) joins pieces first (``join_pieces``); ``hull`` replaces each
    object by its convex hull (an outline closed where a part of its ring is missing);
    ``solidity`` keeps objects covering at least that share of their convex hull;
    ``join_line`` (tiles) joins objects on one line last (``join_lines``).

    Three steps, which a search split into tiles runs apart (``features.tiled``):
    ``prepare_labels`` (holes, specks), ``label_pieces`` (one polygon per label)
    and ``finish_pieces`` (joins, sizes, limits).
    """
    labels, counts, small = prepare_labels(labels, limits, fill_holes, join, join_aligned)
    if not (counts.size > 1 and (~small[1:] & (counts[1:] > 0)).any()):
        return []
    labels = np.where(small[labels], 0, labels)
    pieces = list(label_pieces(labels, counts, kind, transform, tile_size, simplify_tiles).values())
    return finish_pieces(
        pieces,
        tile_size,
        limits,
        measure=measure,
        aspect=aspect,
        join=join,
        join_aligned=join_aligned,
        hull=hull,
        solidity=solidity,
        join_line=join_line,
    )


def near_reach(
    limits: tuple[float | None, ...], join: float | str | None, join_aligned: float | None
) -> int:
    """Tiles within which another label keeps a short piece (``prepare_labels``); 0: none."""
    if join is None or limits[0] is None:
        return 0
    max_w = limits[3]
    reach = int(np.ceil(max_w if join == "width" and max_w else 8 if join == "width" else join))
    return max(reach, int(np.ceil(join_aligned or 0)))


def prepare_labels(
    labels: NDArray[np.int32],
    limits: tuple[float | None, ...],
    fill_holes: bool = True,
    join: float | str | None = None,
    join_aligned: float | None = None,
) -> tuple[NDArray[np.int32], NDArray[np.int64], NDArray[np.bool_]]:
    """Labels with holes filled, their tile counts and which are too small to be objects.

    Cheap bounds: an object's length is at most 2 × its tiles (half a perimeter
    of 4 edges per tile) and a width w needs about w² tiles. With ``join`` a short
    piece with another label within ``near_reach`` tiles is kept (it may be joined)
    unless it is a speck.
    """
    labels = labels.astype(np.int32)
    if fill_holes:
        labels = fill_object_holes(labels)
    counts = np.bincount(labels.ravel())
    min_l, _, min_w, _ = limits
    small = np.zeros(counts.size, dtype=bool)
    if min_l is not None:
        short = 2 * counts < min_l
        reach = near_reach(limits, join, join_aligned)
        if reach:
            short &= ~near_other(labels, reach, counts.size) | (counts < 3)
        small |= short
    if min_w is not None:
        small |= counts < 0.5 * min_w * min_w
    small[0] = False
    return labels, counts, small


def label_pieces(
    labels: NDArray[np.int32],
    counts: NDArray[np.int64],
    kind: str,
    transform: Affine,
    tile_size: float,
    simplify_tiles: float,
) -> dict[int, Feature]:
    """One piece per label: its polygon and the cheap size of its tile staircase
    (area and perimeter); its length is at least the smoothed outline's."""
    out = {}
    for lab, poly in polygons(labels, transform, simplify_tiles * tile_size).items():
        length, width = rectangle_size(poly)
        out[lab] = Feature(kind, poly, float(length), float(width), int(counts[lab]))
    return out


def finish_pieces(
    pieces: list[Feature],
    tile_size: float,
    limits: tuple[float | None, ...],
    *,
    measure: str = "auto",
    aspect: tuple[float | None, float | None] = (None, None),
    join: float | str | None = None,
    join_aligned: float | None = None,
    hull: bool = False,
    solidity: float | None = None,
    join_line: float | None = None,
) -> list[Feature]:
    """Pieces joined (``join``), closed (``hull``), measured and kept within the limits;
    the objects then joined along their lines (``join_line``)."""
    min_l, max_l, min_w, max_w = limits
    if join is not None and len(pieces) > 1:
        single = {id(p) for p in pieces}
        pieces = join_pieces(pieces, join, tile_size, join_aligned)
        if min_l is not None and min_w is not None:
            # the strips bridging gaps join the pieces of an object, they do not make
            # one: a joined object holds at least the tiles of the smallest object
            # the limits admit (its pieces' marked tiles, bridges not counted)
            pieces = [p for p in pieces if id(p) in single or p.tiles >= min_l * min_w]
    if hull:
        pieces = [
            Feature(
                p.kind, p.geometry.convex_hull, *rectangle_size(p.geometry.convex_hull), p.tiles
            )
            for p in pieces
        ]
    feats = []
    lo_a, hi_a = aspect
    for f in pieces:
        if min_l is not None and f.length_m / tile_size < min_l:
            continue
        if measure == "rectangle":
            # the rectangle with the outline's second moments (sides √(12 λ)):
            # unlike area and perimeter, not lengthened by a ragged edge
            length, width = (v * np.sqrt(12) / 4 for v in moment_size(f.geometry))
        else:
            length, width = object_size(_smoothed(f.geometry, tile_size))
        lt, wt = length / tile_size, width / tile_size
        if (min_l is not None and lt < min_l) or (min_w is not None and wt < min_w):
            continue
        if max_w is not None and wt > max_w:
            continue
        if solidity is not None and f.geometry.area < solidity * f.geometry.convex_hull.area:
            continue
        if measure != "rectangle" and length >= 3 * width:
            # an elongated object is no longer than the way through it; its width
            # stays the strip's (a ragged zigzag of 3 m strips is 3 m wide). Measured
            # last: it only shortens, and costs a path search. The way runs through
            # the outline closed across gaps narrower than the object (``closed_across``):
            # a strip beside it, one gap away and touching it at one end, is part of it
            # side by side, not a hairpin to walk out and back along
            length = min(length, path_length(closed_across(f.geometry, width), tile_size / 2))
            lt = length / tile_size
            if min_l is not None and lt < min_l:
                continue
        if max_l is not None and lt > max_l:
            continue
        f = Feature(f.kind, f.geometry, float(length), float(width), f.tiles)
        ratio = f.length_m / max(f.width_m, 1e-9)
        if (lo_a is not None and ratio < lo_a) or (hi_a is not None and ratio > hi_a):
            continue
        feats.append(f)
    if join_line is not None and len(feats) > 1:
        feats = join_lines(feats, join_line, tile_size)
    return feats


def _measured(geom: Polygon | MultiPolygon, tile_size: float) -> tuple[float, float]:
    """(length, width) as ``finish_pieces`` measures an elongated object."""
    length, width = object_size(_smoothed(geom, tile_size))
    if length >= 3 * width:
        length = min(length, path_length(closed_across(geom, width), tile_size / 2))
    return length, width


def join_lines(feats: list[Feature], gap: float, tile_size: float) -> list[Feature]:
    """Objects lying on one line joined across gaps up to ``gap`` tiles.

    Two objects lie on one line when each one's centre is within half the narrower
    one's width of the other's long axis (a straight road found in two pieces: both
    centres on its centre line; two roads side by side or crossing are tens of metres
    off). The gap is bridged by a strip as wide as the narrower object and the joined
    object measured again (its width stays the widest piece's).
    """
    import shapely

    geoms = [f.geometry for f in feats]
    widths = np.array([f.width_m for f in feats])
    axes = np.array([_axis_angle(g) for g in geoms])
    centres = np.array([(g.centroid.x, g.centroid.y) for g in geoms])
    normals = np.stack([-np.sin(axes), np.cos(axes)], axis=1)
    n = len(feats)
    i, j = np.triu_indices(n, 1)
    d = centres[j] - centres[i]
    half = 0.5 * np.minimum(widths[i], widths[j])
    off_i = np.abs((d * normals[i]).sum(axis=1))  # j's centre from i's axis
    off_j = np.abs((d * normals[j]).sum(axis=1))
    ga, gb = np.asarray(geoms, dtype=object)[i], np.asarray(geoms, dtype=object)[j]
    dist = shapely.distance(ga, gb)
    ok = (off_i <= half) & (off_j <= half) & (dist <= gap * tile_size)
    if not ok.any():
        return feats
    parent = list(range(n))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    strips: dict[int, list] = {}
    for k in np.flatnonzero(ok).tolist():
        a, b = root(int(i[k])), root(int(j[k]))
        if a == b:
            continue
        parent[b] = a
        line = shapely.shortest_line(ga[k], gb[k])
        bridge = shapely.buffer(line, half[k], cap_style="flat")
        strips[a] = strips.get(a, []) + strips.pop(b, []) + [bridge]
    groups: dict[int, list[int]] = {}
    for k in range(n):
        groups.setdefault(root(k), []).append(k)
    out = []
    for r, members in groups.items():
        if len(members) == 1:
            out.append(feats[members[0]])
            continue
        geom = unary_union([geoms[m] for m in members] + strips.get(r, []))
        length, _ = _measured(geom, tile_size)
        width = float(widths[members].max())
        tiles = sum(feats[m].tiles for m in members)
        out.append(Feature(feats[members[0]].kind, geom, float(length), width, tiles))
    return out


def near_other(labels: NDArray[np.int32], reach: int, n: int) -> NDArray[np.bool_]:
    """Per label: another label lies within ``reach`` tiles (square neighbourhood)."""
    size = 2 * reach + 1
    hi = ndimage.maximum_filter(labels, size=size)
    big = np.iinfo(np.int32).max
    lo = ndimage.minimum_filter(np.where(labels > 0, labels, big), size=size)
    mixed = (labels > 0) & ((hi != labels) | (lo != labels))
    out = np.zeros(n, dtype=bool)
    out[np.unique(labels[mixed])] = True
    return out


def join_pieces(
    pieces: list[Feature], join: float | str, tile_size: float, aligned: float | None = None
) -> list[Feature]:
    """Pieces closer than ``join`` tiles (``"width"``: the narrower piece's width) joined.

    A pair joins when the gap between them runs within 45° of both pieces'
    long axes: two ends of one broken ditch line up, two parallel ditches lie
    side by side. Pieces lined up end to end (long axes within 20° of each
    other and of the gap, each piece at least 1.5 times as long as wide), or whose
    facing ends meet (``_ends_meet``), join across gaps up to ``aligned`` tiles. Sizes
    here are the cheap staircase ones (``rectangle_size``); ``objects_from_labels``
    measures the objects that remain.
    """
    import shapely
    from shapely import STRtree

    geoms = [p.geometry for p in pieces]
    widths = np.array([p.width_m for p in pieces])
    reach = widths.max() if join == "width" else float(join) * tile_size
    long_gap = 0.0 if aligned is None else float(aligned) * tile_size
    reach = max(reach, long_gap)
    tree = STRtree(geoms)
    a, b = tree.query(geoms, predicate="dwithin", distance=reach)
    keep = a < b
    a, b = a[keep], b[keep]
    if a.size == 0:
        return pieces
    ga, gb = np.asarray(geoms, dtype=object)[a], np.asarray(geoms, dtype=object)[b]
    gap = shapely.distance(ga, gb)
    allowed = np.minimum(widths[a], widths[b]) if join == "width" else np.full(a.size, reach)
    ok = gap <= np.maximum(allowed, long_gap)
    axes = np.array([_axis_angle(g) for g in geoms])
    lines = shapely.shortest_line(ga[ok], gb[ok])
    xy = shapely.get_coordinates(lines).reshape(-1, 2, 2)
    d = xy[:, 1] - xy[:, 0]
    phi = np.arctan2(d[:, 1], d[:, 0])
    tiny = np.hypot(d[:, 0], d[:, 1]) < 0.5 * tile_size
    ax_a, ax_b = axes[a[ok]], axes[b[ok]]
    short = gap[ok] <= allowed[ok]
    along = short & (_angle_diff(phi, ax_a) <= np.pi / 4) & (_angle_diff(phi, ax_b) <= np.pi / 4)
    lined = np.radians(20)
    # a piece as long as wide (by its second moments, under 1.5 times: a speck, or a
    # blob of marks) has no long axis to line up by: a 20 x 7 m piece of a road cut's
    # marks (16 x 11 m by its moments), 19 m past a straight 3.5 m ditch's end and 11 m
    # off its line, had an axis 4 degrees off the ditch's and the gap between the two
    # staircases read within 20 degrees of both, and the 151 m ditch ran on into it,
    # 203 m long. Such a piece is joined end to end only where the facing ends meet
    # (without ``aligned`` every gap is shorter than the width, where ``along`` holds
    # whatever this rule does)
    axial = np.ones(len(geoms), dtype=bool)
    if long_gap > 0:
        sizes = np.array([moment_size(g) for g in geoms])
        axial = sizes[:, 0] >= 1.5 * sizes[:, 1]
    end_to_end = (
        axial[a[ok]]
        & axial[b[ok]]
        & (_angle_diff(ax_a, ax_b) <= lined)
        & (_angle_diff(phi, ax_a) <= lined)
        & (_angle_diff(phi, ax_b) <= lined)
    )
    # the gap's direction between two staircase outlines follows the tile grid (their
    # closest points lie along a row or a column), and a winding piece's whole axis is
    # not its direction at its end: read both at the facing ends instead (``_ends_meet``)
    # (within 45 degrees across a gap shorter than the width, as ``along``; 20 across a
    # longer one, as ``end_to_end``). Only where pieces are joined end to end (``aligned``,
    # the ditch filters): a ridge's or a road's end part, 3 of its widths of 4-12 m, reaches
    # tens of metres, and pieces of a ridge beside one another read as ends meeting
    # (Topography.laz: a 79 m ridge joined to a 45 m strip 16 m off its line and lost)
    unjoined = ~((tiny & short) | along | end_to_end) & (long_gap > 0)
    for n in np.flatnonzero(unjoined).tolist():
        i, j = int(a[ok][n]), int(b[ok][n])
        turn = np.pi / 4 if short[n] else lined
        if short[n] or gap[ok][n] <= long_gap:
            end_to_end[n] = _ends_meet(geoms[i], geoms[j], xy[n, 0], xy[n, 1], widths[[i, j]], turn)
    keep_pair = (tiny & short) | along | end_to_end
    pairs = np.flatnonzero(ok)[keep_pair]
    # a gap longer than the short join is bridged by a strip as wide as the narrower piece
    strips = {
        int(k): shapely.buffer(line, w / 2, cap_style="flat")
        for k, line, w, sh in zip(
            pairs.tolist(),
            lines[keep_pair],
            np.minimum(widths[a], widths[b])[pairs],
            short[keep_pair],
            strict=True,
        )
        if not sh
    }
    parent = list(range(len(pieces)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    bridged: dict[int, float] = {}
    extra: dict[int, list] = {}
    for k in pairs.tolist():
        ri, rj = root(int(a[k])), root(int(b[k]))
        if ri != rj:
            parent[rj] = ri
            extra[ri] = extra.get(ri, []) + extra.pop(rj, [])
            if k in strips:
                extra[ri].append(strips[k])
                bridged[ri] = max(bridged.get(ri, 0.0), bridged.pop(rj, 0.0))
            else:
                bridged[ri] = max(bridged.get(ri, 0.0), bridged.pop(rj, 0.0), float(gap[k]))
    groups: dict[int, list[int]] = {}
    for i in range(len(pieces)):
        groups.setdefault(root(i), []).append(i)
    out = []
    for r, members in groups.items():
        if len(members) == 1:
            out.append(pieces[members[0]])
            continue
        geom = _bridge([geoms[m] for m in members] + extra.get(r, []), bridged.get(r, 0.0))
        length, width = rectangle_size(geom)
        tiles = sum(pieces[m].tiles for m in members)
        out.append(Feature(pieces[0].kind, geom, float(length), float(width), tiles))
    return out


#: widths behind a piece's facing end over which ``_ends_meet`` reads its direction there
END_REACH = 3


def _ends_meet(
    ga: Polygon | MultiPolygon,
    gb: Polygon | MultiPolygon,
    pa: NDArray,
    pb: NDArray,
    widths: NDArray,
    turn: float,
) -> bool:
    """Whether pieces ``ga`` and ``gb``, whose outlines come closest at ``pa`` and ``pb``,
    meet end to end: the way from one facing end to the other continues each piece's
    direction at its end within ``turn`` (radians).

    A piece's end is its part within ``END_REACH`` of its own widths of its closest
    point; that point must lie ahead of the part (the part's centroid at least a quarter
    of that reach behind it along the part's axis: an end, not a side), and the way runs
    between the parts' centroids, so it follows the object's centre line rather than the
    tile grid's staircase. A piece too short to show a direction there (its end part
    less than 1.5 times as long as wide by its second moments: a speck one tile across
    reads 1, a straight end of 3 widths 3) gives none and only the other's is asked; two
    such pieces do not meet. So a straight or gently winding ditch broken into pieces
    joins (the two ends turn by at most twice the limit across the gap), and two
    ditches side by side, or an end against another's side, do not. One end's line must
    also pass the other end part's centroid closer than the two pieces' widths together:
    a jog under the width joins, a ditch beside another a road's width off does not.
    Where one end part shows no direction, the other's line, continued straight, must
    pass within that piece's width of the part's outline."""
    from shapely.geometry import Point

    ends: list[tuple[NDArray, NDArray | None]] = []
    parts = []
    for g, p, w in ((ga, pa, widths[0]), (gb, pb, widths[1])):
        r = END_REACH * w
        local = g.intersection(Point(p).buffer(r))
        if not isinstance(local, Polygon | MultiPolygon) or local.area <= 0:
            return False
        parts.append(local)
        m = np.asarray(local.centroid.coords[0])
        length, width = moment_size(local)
        if length < 1.5 * width:
            ends.append((m, None))
            continue
        ang = _axis_angle(local)
        u = np.array([np.cos(ang), np.sin(ang)])
        back = float(np.dot(p - m, u))
        if abs(back) < r / 4:
            return False
        ends.append((m, u if back > 0 else -u))
    (ma, ua), (mb, ub) = ends
    if ua is None and ub is None:
        return False
    way = mb - ma
    norm = float(np.hypot(*way))
    if norm == 0:
        return False
    way = way / norm
    if not all(
        d is None or float(np.dot(d, v)) >= np.cos(turn) for d, v in ((ua, way), (ub, -way))
    ):
        return False
    # and one piece, continued straight along its end's direction, runs into the other's
    # end: the other end part's centroid lies off that line by less than the two pieces'
    # widths together, as far apart as two pieces of one channel that wide can lie (a
    # 3 m ditch was found as 1.5 and 1.9 m pieces on its two sides, 2.8 m apart across
    # 22 m; their mean width split it). Within the turn alone, two ditches side by side
    # a road's width apart, their ends staggered by a long gap, read as meeting
    across = [abs(d[0] * way[1] - d[1] * way[0]) * norm for d in (ua, ub) if d is not None]
    if ua is not None and ub is not None:
        return min(across) < float(widths.sum())
    # an end part showing no direction (a speck, or a blob as long as wide) has no line
    # of its own to lie on beside the other, and its width says nothing of the channel's:
    # the other end's line, continued straight, must pass within that piece's own width
    # of the part's outline (on the channel's far bank at most: a 3 m ditch found as
    # 1.5-2 m pieces along its two banks, a 2 m speck's outline 1.05 m off a 1.8 m
    # piece's line; seen job DTMs: specks 0.1-0.7 m off a 1.9 m ditch's line). With the
    # blob's width in the two widths' allowance, a 20 x 7 m piece of a road cut's marks
    # 19 m past a 3.5 m ditch's end, its centroid 12 m off the ditch's line, was only 2 m
    # past it (and 21 degrees against 20 off the ditch's direction); its outline lies
    # 5.9 m off the ditch's line
    k = 0 if ua is not None else 1
    m, d = (ma, ua) if k == 0 else (mb, ub)
    assert d is not None
    ray = LineString([m, m + d * (norm + END_REACH * float(widths[1 - k]))])
    return bool(ray.distance(parts[1 - k]) <= widths[k])


def _axis_angle(poly: Polygon | MultiPolygon) -> float:
    """Direction (radians, mod π) of the long axis of ``poly``'s second area moments."""
    parts = poly.geoms if isinstance(poly, MultiPolygon) else [poly]
    cx, cy = poly.centroid.x, poly.centroid.y
    area = sxx = syy = sxy = 0.0
    for p in parts:
        xy = np.asarray(p.exterior.coords) - (cx, cy)
        x0, y0, x1, y1 = xy[:-1, 0], xy[:-1, 1], xy[1:, 0], xy[1:, 1]
        cr = x0 * y1 - x1 * y0
        area += cr.sum() / 2
        sxx += (cr * (y0 * y0 + y0 * y1 + y1 * y1)).sum() / 12
        syy += (cr * (x0 * x0 + x0 * x1 + x1 * x1)).sum() / 12
        sxy += (cr * (x0 * y1 + 2 * x0 * y0 + 2 * x1 * y1 + x1 * y0)).sum() / 24
    sign = 1.0 if area >= 0 else -1.0  # rings may run either way
    return float(0.5 * np.arctan2(2 * sign * sxy, sign * (syy - sxx))) % np.pi


def _angle_diff(a: NDArray, b: NDArray) -> NDArray:
    d = np.abs(a - b) % np.pi
    return np.minimum(d, np.pi - d)


def _bridge(geoms: list, gap: float) -> Polygon | MultiPolygon:
    """Union of ``geoms`` closed across gaps up to ``gap`` (one outline where they line up)."""
    g = unary_union(geoms)
    if gap <= 0 or not isinstance(g, MultiPolygon):
        return g
    r = gap / 2 + 1e-6
    closed = g.buffer(r, join_style="mitre").buffer(-r, join_style="mitre")
    return closed if not closed.is_empty else g
