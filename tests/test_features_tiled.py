"""Terrain objects searched core by core (with halos) equal one search over the whole DTM."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.typing import NDArray
from rasterio import Affine
from shapely.geometry import box

from terrasift.synthetic.feature_family import make_family_scene, surface_raster
from terrasift.workers.categories import CategoryParams, measure_noise, measure_slope_noise
from terrasift.workers.features import (
    DtmHeights,
    categories_for,
    detect_features,
    resolve_filters,
)
from terrasift.workers.features.tiled import merge_pieces, tile_pieces, window_reach

CELL = 0.5


def _measured(dtm: np.ndarray) -> CategoryParams:
    """Default category parameters with the noise and slope noise measured on ``dtm``."""
    cp = CategoryParams()
    return cp.model_copy(
        update={
            "noise": measure_noise(dtm, CELL, cp),
            "slope_noise": measure_slope_noise(dtm, CELL, cp),
        }
    )


@pytest.fixture(scope="module")
def scene() -> dict:
    dtm = surface_raster(make_family_scene(0), CELL)  # 320 m: every kind of object
    dtm = dtm + np.random.default_rng(1).normal(0, 0.02, dtm.shape)
    transform = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    filters = resolve_filters("all")
    cp = _measured(dtm)
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    whole = detect_features(
        cats, filters, transform, cats.tile_size, stepped=stepped, dtm=dtm
    ).objects
    return {"dtm": dtm, "t": transform, "filters": filters, "cp": cp, "whole": whole}


def _key(f) -> tuple:
    c = f.geometry.centroid
    return (f.kind, f.tiles, round(c.x, 3), round(c.y, 3))


def _tiled(scene: dict, n: int, halo: int | None, edges: list[int] | None = None) -> list:
    dtm = scene["dtm"]
    if edges is None:
        edges = np.linspace(0, dtm.shape[0], n + 1).astype(int).tolist()
    n = len(edges) - 1
    pieces = []
    for i in range(n):
        for j in range(n):
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            pieces += tile_pieces(
                lambda a, b, c, d: dtm[a:b, c:d],
                dtm.shape,
                scene["t"],
                core,
                scene["filters"],
                scene["cp"],
                halo=halo,
            )
    heights = DtmHeights.of(dtm, scene["t"])
    return merge_pieces(pieces, scene["filters"], scene["cp"], CELL, dtm=heights).objects


def test_cores_without_halo_grow_to_the_whole_objects(scene: dict) -> None:
    """Halo 0: every object across a core edge is found by growing the window around it."""
    whole = sorted(scene["whole"], key=_key)
    kinds = {f.kind for f in whole}
    assert {"hill", "road", "ditch", "ridge"} <= kinds, kinds
    # the test means something: objects cross the 2 x 2 cores' edges
    t = scene["t"]
    mid_x, mid_y = t @ (scene["dtm"].shape[1] // 2, scene["dtm"].shape[0] // 2)
    crossing = [f for f in whole if f.geometry.intersects(box(mid_x - 0.01, 0, mid_x + 0.01, 1e8))]
    crossing += [f for f in whole if f.geometry.intersects(box(0, mid_y - 0.01, 1e7, mid_y + 0.01))]
    assert crossing
    tiled = sorted(_tiled(scene, 2, 0), key=_key)
    assert [_key(f) for f in tiled] == [_key(f) for f in whole]
    for a, b in zip(tiled, whole, strict=True):
        assert a.geometry.hausdorff_distance(b.geometry) < 1e-6
        assert abs(a.length_m - b.length_m) < 1e-6 and abs(a.width_m - b.width_m) < 1e-6


def test_window_reach_covers_the_widest_filter() -> None:
    cp = CategoryParams()
    ridge = window_reach(resolve_filters("ridge"), cp, CELL)
    assert window_reach(resolve_filters("all"), cp, CELL) == ridge
    # the regional window (120 m) alone reaches 60 m and more
    assert ridge * CELL > 60


def test_cores_one_tile_thin_without_halo_search_as_the_others(scene: dict) -> None:
    """Halo 0 and cores one 2 m tile thin along the DTM's edges (their first window is
    one tile of the regional median's coarser sampling): no error, and the objects
    of all cores are still the whole DTM's."""
    dtm = scene["dtm"]
    n = dtm.shape[0]
    tiled = sorted(_tiled(scene, 0, 0, [0, 4, n - 4, n]), key=_key)
    whole = sorted(scene["whole"], key=_key)
    assert [_key(f) for f in tiled] == [_key(f) for f in whole]


def test_flat_marks_across_the_dtm_do_not_grow_a_rectangle_filter_s_window(scene: dict) -> None:
    """Level tiles lie scattered over the whole scene (their support once joined across
    the DTM, so every window grew to all of it); a flat area's object is its cover:
    cores away from flat areas keep their first window, and the objects of cores with
    that halo are still the whole DTM's."""
    from terrasift.workers.features.tiled import search_core

    dtm, cp = scene["dtm"], scene["cp"]
    filters = resolve_filters("flat-area")
    halo = window_reach(filters, cp, CELL) + 16
    n = dtm.shape[0]
    edges = [0, 64, n // 2, n - 64, n]
    pieces, kept = [], 0
    for i in range(4):
        for j in range(4):
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            found, seen = search_core(
                lambda a, b, c, d: dtm[a:b, c:d],
                dtm.shape,
                scene["t"],
                core,
                filters,
                cp,
                halo=halo,
            )
            pieces += found
            start = tuple(
                max(0, min(n, v))
                for v in (core[0] - halo, core[1] - halo, core[2] + halo, core[3] + halo)
            )
            kept += seen == start
    assert kept >= 2, kept
    whole = sorted((f for f in scene["whole"] if f.kind == "flat-area"), key=_key)
    assert whole  # the scene holds flat areas
    tiled = sorted(merge_pieces(pieces, filters, cp, CELL).objects, key=_key)
    assert [_key(f) for f in tiled] == [_key(f) for f in whole]


def _around(kind: str, size: float) -> NDArray[np.float64]:
    """A ``size`` m square DTM of family scene 0 centred on its first object of
    ``kind``, with 2 cm of noise."""
    scene = make_family_scene(0)
    n = int(size / CELL)
    c = (np.arange(n) + 0.5) * CELL
    at = next(t for t in scene.truth if t.kind == kind).polygon.centroid
    x, y = np.meshgrid(at.x - size / 2 + c, at.y + size / 2 - c)
    dtm = scene.surface(x.ravel(), y.ravel()).reshape(n, n)
    return dtm + np.random.default_rng(1).normal(0, 0.02, dtm.shape)


def _searched_in_nine(dtm: NDArray[np.float64], t: Affine, filters, cp, fp) -> list:
    """The pieces found by searching ``dtm`` as 3 × 3 cores with a capped window
    (16 tiles), so objects larger than a core are searched in parts."""
    from terrasift.workers.features.tiled import search_core

    halo, cap = window_reach(filters, cp, CELL) + 8, 16
    edges = np.linspace(0, dtm.shape[0], 4).astype(int).tolist()
    pieces = []
    for i in range(3):
        for j in range(3):
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            pieces += search_core(
                lambda a, b, c, d: dtm[a:b, c:d], dtm.shape, t, core, filters, cp, fp, halo, cap
            )[0]
    return pieces


def _plain_with_road_and_ditch(size: float) -> NDArray[np.float64]:
    """A level plain (0.2 % tilt, 2 cm noise) crossed west to east by a road on a 0.8 m
    embankment (6 m top, 1 : 1.5 sides, turned 3°) and north to south by a ditch
    0.6 m deep (1 m floor, 1 : 1 banks, turned 5°): all three span the whole DTM."""
    n = int(size / CELL)
    y, x = (np.mgrid[0:n, 0:n] + 0.5) * CELL
    z = 100.0 + 0.002 * x
    d = np.abs((y - 0.3 * size) - 0.05 * (x - size / 2))
    z = z + np.clip(0.8 - np.maximum(d - 3.0, 0) / 1.5, 0, None)
    d = np.abs((x - 0.55 * size) + 0.08 * (y - size / 2))
    z = z - np.clip(0.6 - np.maximum(d - 0.5, 0), 0, None)
    return z + np.random.default_rng(0).normal(0, 0.02, z.shape)


@pytest.mark.parametrize(
    ("names", "size", "n"), [("flat-area", 400.0, 4), ("road,ditch", 360.0, 3)]
)
def test_objects_as_large_as_the_dtm_are_searched_in_parts_within_a_capped_window(
    names: str, size: float, n: int
) -> None:
    """A level plain (one flat area) and a road and a ditch across the whole DTM: with a
    cap every core's window stays within the core, its halo and the cap (without one
    it grows to the whole DTM), the objects are searched in parts (``Cut``) and the
    parts joined equal the whole DTM's objects (unsimplified outlines: the same
    tiles, outline, length and width)."""
    from terrasift.workers.features import FeatureParams
    from terrasift.workers.features.tiled import search_core, window_align

    dtm = _plain_with_road_and_ditch(size)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    filters = resolve_filters(names)
    cp = _measured(dtm)
    fp = FeatureParams(simplify_tiles=0)
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped, dtm=dtm).objects
    assert sorted(f.kind for f in whole) == sorted(names.split(","))
    assert all(f.length_m > 0.9 * size for f in whole)  # each spans the DTM
    reach = window_reach(filters, cp, CELL)
    halo, cap = reach + 8, 32
    align = window_align(filters, cp, CELL)
    ext = max(halo, reach + 2 * align) + cap
    edges = np.linspace(0, dtm.shape[0], n + 1).astype(int).tolist()
    pieces, largest = [], 0
    for i in range(n):
        for j in range(n):
            core = (edges[i], edges[j], edges[i + 1], edges[j + 1])
            found, seen = search_core(
                lambda a, b, c, d: dtm[a:b, c:d], dtm.shape, t, core, filters, cp, fp, halo, cap
            )
            pieces += found
            for a in (0, 1):  # the window: within the core, its halo and the cap
                assert seen[a] >= core[a] - ext - align and seen[a + 2] <= core[a + 2] + ext
            largest = max(largest, (seen[2] - seen[0]) * (seen[3] - seen[1]))
    assert largest < dtm.size
    # without the cap a core's window grows to the whole DTM around these objects
    core = (edges[1], edges[1], edges[2], edges[2])
    seen = search_core(lambda a, b, c, d: dtm[a:b, c:d], dtm.shape, t, core, filters, cp, fp, halo)[
        1
    ]
    assert seen == (0, 0, *dtm.shape)
    assert sum(p.cut is not None for p in pieces) >= n * n // 2
    tiled = merge_pieces(pieces, filters, cp, CELL, fp, dtm=DtmHeights.of(dtm, t)).objects
    assert sorted(_key(f) for f in tiled) == sorted(_key(f) for f in whole)
    for a in whole:
        (b,) = [f for f in tiled if _key(f) == _key(a)]
        assert a.geometry.hausdorff_distance(b.geometry) < 1e-6
        assert abs(a.length_m - b.length_m) < 1e-6 and abs(a.width_m - b.width_m) < 1e-6


@pytest.mark.parametrize("names", ["ditch", "ridge", "road", "flat-area", "all"])
def test_categories_made_block_by_block_equal_the_window_s(scene: dict, names: str) -> None:
    """A grown window's categories are made in blocks read with a margin of the
    categories' reach: every band of every grid equals ``categories_for`` over the
    whole window (an aligned window, ends off the block grid, a nodata hole)."""
    from dataclasses import fields

    from terrasift.workers.features.tiled import blocked_categories, window_align

    dtm = scene["dtm"].copy()
    dtm[300:340, 200:260] = np.nan
    filters = resolve_filters(names)
    cp = scene["cp"]
    align = window_align(resolve_filters("all"), cp, CELL)
    rect = (align, 2 * align, dtm.shape[0] - 5, dtm.shape[1] - 3)
    whole, whole_stepped = categories_for(
        dtm[rect[0] : rect[2], rect[1] : rect[3]], CELL, filters, cp, (rect[0], rect[1])
    )
    reads: list[tuple[int, int, int, int]] = []

    def read(a: int, b: int, c: int, d: int) -> NDArray:
        reads.append((a, b, c, d))
        return dtm[a:b, c:d]

    cats, stepped = blocked_categories(read, rect, filters, cp, CELL, block=100)
    assert len(reads) >= 9  # in blocks, none the whole window
    assert all(
        (b - a) * (d - c) < (rect[2] - rect[0]) * (rect[3] - rect[1]) for a, b, c, d in reads
    )
    assert stepped.keys() == whole_stepped.keys()
    for a, b in [(whole, cats)] + [(whole_stepped[k], stepped[k]) for k in whole_stepped]:
        for f in fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert x == y, f.name


def test_a_grown_window_holds_one_filter_s_grids_and_never_the_start_window_s(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A square's memory is the larger of its start window (every filter's grids) and
    its largest grown window (one filter's), not their sum: every filter is searched
    on the start window first, and no window's grids are alive when another window
    is read. Road, ditch and flat area across a level plain grow every window."""
    import gc
    import weakref

    from terrasift.workers.features import tiled

    dtm = _plain_with_road_and_ditch(300.0)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    filters = resolve_filters("road,ditch,flat-area")
    cp = _measured(dtm)
    made: list[tuple[int, weakref.ref]] = []
    reads: list[tuple[int, int, int, int]] = []
    real = tiled.categories_for

    def counted(window, cell, todo, params, origin=(0, 0)):  # type: ignore[no-untyped-def]
        cats, stepped = real(window, cell, todo, params, origin)
        made.append((len(todo), weakref.ref(cats)))
        made.extend((len(todo), weakref.ref(c)) for c in stepped.values())
        return cats, stepped

    def read(a: int, b: int, c: int, d: int) -> NDArray:
        gc.collect()
        assert all(ref() is None for _, ref in made), "a window's grids outlive it"
        reads.append((a, c, b, d))
        return dtm[a:b, c:d]

    monkeypatch.setattr(tiled, "categories_for", counted)
    n = dtm.shape[0]
    core = (n // 3, n // 3, 2 * n // 3, 2 * n // 3)
    for cap in (None, 32):
        made.clear(), reads.clear()
        tiled.search_core(read, dtm.shape, t, core, filters, cp, None, 0, cap)
        assert len(reads) >= 3, reads  # the start window and at least two grown ones
        assert len(set(reads)) >= 2 and reads[0] not in reads[1:]  # the start: once
        assert made[0][0] == len(filters) and all(k == 1 for k, _ in made[len(filters) :])


def test_surround_reads_the_same_ground_around_an_object_in_every_core() -> None:
    """``surround`` reads tiles around an object: on a hummocky slope where it keeps some
    pieces and drops others, cores without halo still give the whole DTM's objects."""
    from terrasift.synthetic.feature_family import make_rough_scene
    from terrasift.workers.features import format_filter, parse_filter

    dtm = surface_raster(make_rough_scene(3, size=160.0), CELL)
    dtm = dtm + np.random.default_rng(1).normal(0, 0.03, dtm.shape)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    text = format_filter(resolve_filters("ditch")[0])
    assert "surround 6m 0.5" in text
    filters = [parse_filter(text.replace("surround 6m 0.5", "surround 6m 0.98"), "ditch")]
    plain = [parse_filter(text.replace("surround 6m 0.5\n", ""), "ditch")]
    cp = _measured(dtm)
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    whole = detect_features(cats, filters, t, cats.tile_size, stepped=stepped).objects
    n_plain = len(detect_features(cats, plain, t, cats.tile_size, stepped=stepped).objects)
    assert 0 < len(whole) < n_plain  # some pieces kept, some dropped
    scene = {"dtm": dtm, "t": t, "filters": filters, "cp": cp}
    tiled = sorted(_tiled(scene, 2, 0), key=_key)
    assert [_key(f) for f in tiled] == sorted(_key(f) for f in whole)


def test_surround_judges_an_object_searched_in_parts_by_its_whole_ring() -> None:
    """With a capped window the hollows of a hummocky slope are searched in parts
    (``Cut``); ``surround`` then judges the ground around the joined label, so the
    objects kept and dropped are the whole DTM's."""
    from terrasift.synthetic.feature_family import make_rough_scene
    from terrasift.workers.features import FeatureParams, format_filter, parse_filter

    dtm = surface_raster(make_rough_scene(3, size=160.0), CELL)
    dtm = dtm + np.random.default_rng(1).normal(0, 0.03, dtm.shape)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    text = format_filter(resolve_filters("ditch")[0])
    filters = [parse_filter(text.replace("surround 6m 0.5", "surround 6m 0.98"), "ditch")]
    cp = _measured(dtm)
    fp = FeatureParams(simplify_tiles=0)
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped).objects
    assert whole
    pieces = _searched_in_nine(dtm, t, filters, cp, fp)
    cut = [p for p in pieces if p.cut is not None]
    assert cut and all(p.cut.ring is not None for p in cut)
    tiled = merge_pieces(pieces, filters, cp, CELL, fp).objects
    assert sorted(_key(f) for f in tiled) == sorted(_key(f) for f in whole)


def test_a_label_touching_itself_at_a_corner_is_joined_with_its_holes() -> None:
    """A flat area (holes kept) whose tiles enclose a gap around an island of its own,
    touching it at one corner, cut by a core edge: the parts' union is two polygons
    touching at a point, which the corner buffer does not join, so the bridging
    buffer used to fill the gap. The joined outline is now the one a single search
    traces for the same tiles (exact and simplified)."""
    from rasterio.features import shapes
    from shapely.geometry import shape
    from shapely.ops import unary_union

    from terrasift.workers.features import FeatureParams
    from terrasift.workers.features.objects import Feature, polygons
    from terrasift.workers.features.tiled import Cut, Piece, _join_cuts, _resolved

    lab = np.zeros((14, 18), np.int32)
    lab[1:13, 1:17] = 1
    lab[3:11, 3:15] = 0  # the gap
    lab[4:10, 4:14] = 1  # the island
    lab[3, 3] = 1  # the ring touches the island at one corner: (3, 3) and (4, 4)
    edge = 9  # core columns [0, 9) and [9, 18)
    grid = (2.0, 0.0, 500_000.0, 0.0, -2.0, 5_400_000.0)
    at = Affine(*grid)
    flt = _resolved(resolve_filters("flat-area")[0], CategoryParams(), CELL)
    for simplify in (0.0, 0.5):
        fp = FeatureParams(simplify_tiles=simplify)
        parts = []
        for c0, c1 in ((0, edge), (edge, lab.shape[1])):
            mine = np.zeros_like(lab)
            mine[:, c0:c1] = lab[:, c0:c1]
            other = (lab > 0) & (mine == 0)
            polys = [shape(g) for g, _ in shapes(mine, mask=mine > 0, connectivity=8)]
            tiles = {(int(r), int(c)) for r, c in zip(*np.nonzero(mine), strict=True)}
            cut = Cut(
                grid,
                unary_union(polys),
                frozenset(tiles),
                frozenset((int(r), int(c)) for r, c in zip(*np.nonzero(other), strict=True)),
                False,
                None,
                None,
            )
            key = min(tiles)
            feat = Feature("flat-area", cut.polygon, 0.0, 0.0, len(tiles))
            parts.append(Piece(0, key, feat, cut))
        (joined,) = _join_cuts(parts, flt, fp)
        (whole,) = polygons(lab, at, simplify * 2.0).values()
        assert joined.feature.tiles == int(lab.sum())
        assert joined.feature.geometry.area == pytest.approx(whole.area, abs=1e-6)
        assert joined.feature.geometry.symmetric_difference(whole).area < 1e-6
        assert joined.feature.geometry.hausdorff_distance(whole) < 1e-6


def test_enclosed_judges_a_pond_searched_in_parts_by_its_whole_rim() -> None:
    """With a capped window a pond is searched in parts (``Cut``); ``enclosed`` then
    judges the rim of the joined label around its whole centre, so the ponds kept are
    the whole DTM's, asking for 7 of the 8 sectors and for all 8."""
    from terrasift.workers.features import FeatureParams, format_filter, parse_filter

    dtm = _around("pond", 160.0)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    text = format_filter(resolve_filters("pond")[0])
    assert "enclosed 8m 7" in text
    cp = _measured(dtm)
    fp = FeatureParams(simplify_tiles=0)
    for sectors in (7, 8):
        filters = [parse_filter(text.replace("enclosed 8m 7", f"enclosed 8m {sectors}"), "pond")]
        cats, stepped = categories_for(dtm, CELL, filters, cp)
        whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped).objects
        pieces = _searched_in_nine(dtm, t, filters, cp, fp)
        cut = [p for p in pieces if p.cut is not None]
        assert cut and all(p.cut.rim is not None for p in cut)
        tiled = merge_pieces(pieces, filters, cp, CELL, fp).objects
        assert sorted(_key(f) for f in tiled) == sorted(_key(f) for f in whole)
        if sectors == 7:
            assert len(whole) == 1  # the pond


def test_isolated_judges_a_hill_searched_in_parts_by_its_whole_rim() -> None:
    """With a capped window a hill is searched in parts (``Cut``); ``isolated`` then
    judges the rim of the joined label around its whole centre, so the hills kept are
    the whole DTM's: the built-in filter's (kept) and one that reads 16 m around and
    allows none of it to run on (dropped: the far ring reaches the background's waves)."""
    from terrasift.workers.features import FeatureParams, format_filter, parse_filter

    dtm = _around("hill", 140.0)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    text = format_filter(resolve_filters("hill")[0])
    assert "isolated 4m 0.1" in text
    cp = _measured(dtm)
    fp = FeatureParams(simplify_tiles=0)
    for rule, kept in (("isolated 4m 0.1", 1), ("isolated 16m 0.005", 0)):
        filters = [parse_filter(text.replace("isolated 4m 0.1", rule), "hill")]
        cats, stepped = categories_for(dtm, CELL, filters, cp)
        whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped).objects
        assert len(whole) == kept
        pieces = _searched_in_nine(dtm, t, filters, cp, fp)
        cut = [p for p in pieces if p.cut is not None]
        assert cut and all(p.cut.fall is not None for p in cut)
        tiled = merge_pieces(pieces, filters, cp, CELL, fp).objects
        assert sorted(_key(f) for f in tiled) == sorted(_key(f) for f in whole)


def test_clear_share_spares_an_object_searched_in_parts_by_its_whole_size() -> None:
    """``clear-share``'s noise multiple: a shallow winding ditch (feature family seed 112,
    5.7 m wide, 0.32 m deep on 5 %) whose banks are mostly not clearly past the flatness
    threshold is kept by its size; searched in parts with a capped window, the parts'
    tiles add up to the whole label's, and the objects are the whole DTM's."""
    from terrasift.workers.features import FeatureParams

    scene = make_family_scene(112)
    ditch = next(t for t in scene.truth if t.kind == "ditch" and t.length_m > 150)
    x0, y0, x1, y1 = ditch.polygon.buffer(12).bounds
    n, m = int((y1 - y0) / CELL), int((x1 - x0) / CELL)
    c = (np.arange(max(n, m)) + 0.5) * CELL
    x, y = np.meshgrid(x0 + c[:m], y1 - c[:n])
    dtm = scene.surface(x.ravel(), y.ravel()).reshape(n, m)
    dtm = dtm + np.random.default_rng([7, 112]).normal(0, scene.noise, dtm.shape)
    t = Affine(CELL, 0, 500_000.0, 0, -CELL, 5_400_000.0)
    filters = resolve_filters("ditch")
    cp = _measured(dtm)
    fp = FeatureParams(simplify_tiles=0)
    cats, stepped = categories_for(dtm, CELL, filters, cp)
    assert cats.flat_sigmas > filters[0].clear_exempt
    whole = detect_features(cats, filters, t, cats.tile_size, fp, stepped=stepped).objects
    assert [f.kind for f in whole] == ["ditch"] and whole[0].length_m > 0.75 * ditch.length_m
    judged = [dataclasses.replace(filters[0], clear_exempt=None)]
    assert not detect_features(cats, judged, t, cats.tile_size, fp, stepped=stepped).objects
    pieces = _searched_in_nine(dtm, t, filters, cp, fp)
    assert any(p.cut is not None and p.cut.clear_exempt is not None for p in pieces)
    tiled = merge_pieces(pieces, filters, cp, CELL, fp).objects
    assert sorted(_key(f) for f in tiled) == sorted(_key(f) for f in whole)
