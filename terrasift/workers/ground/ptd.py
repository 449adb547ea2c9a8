"""Ground by progressive TIN densification (DESIGN §5.2; the TerraScan-style
filter of the rotation seed, after Axelsson 2000).

Seeds are the lowest point of every ``max_building_size`` cell, with isolated
low outliers removed (candidates that stand alone under the cloud give way to
the next lowest point of their cell). A TIN through the seeds is then densified
in rounds: a point is accepted when its perpendicular distance to the facet it
falls in is below ``iteration_distance`` and its angles to the facet's vertices
are below ``iteration_angle``; facets steeper than ``terrain_angle`` take no
points. Each round re-triangulates and accepts at most one point per facet (the
one with the smallest angle), so a facet's estimate never jumps by more than
one point; it stops when a round adds nothing. A vertex standing below all its
neighbours (a return under the terrain) leaves the TIN before the next round.
Parts of the TIN that stand above the rest behind steps all round (roofs wider
than a seed cell) are then dropped, and one final pass labels every other
point against the TIN.

Speed: the rounds only ever see the lowest point of each ``min_spacing``
cell (the TIN holds no more vertices than that anyway), so a round judges one
candidate per cell, not the cloud; every other point is judged once, against
the final TIN. Each facet's plane is computed once per TIN, and a point's angle
is only worked out where it can decide the test. Points are located with
``find_simplex`` in a spatially coherent order (it walks from the previous hit).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import Delaunay, QhullError, cKDTree

from terrasift.workers.bins import ANCHOR, Grid, lowest_per_bin
from terrasift.workers.ground.lowpoints import LowPointParams, isolated_low_points
from terrasift.workers.ground.tin import Tin
from terrasift.workers.registry import StageParams, register
from terrasift.workers.surface import spatial_order


class PtdParams(StageParams):
    """Parameters of progressive TIN densification (seed Table 1 names)."""

    terrain_angle: float = Field(80.0, gt=0.0, le=90.0)
    """Degrees: facets steeper than this take no new points."""
    iteration_angle: float = Field(30.0, gt=0.0, le=60.0)
    """Degrees: largest angle between a point, its projection on the facet and a facet vertex."""
    iteration_distance: float = Field(1.5, gt=0.0, le=50.0)
    """Metres: largest perpendicular distance from a point to its facet."""
    max_building_size: float = Field(12.0, ge=1.0, le=1000.0)
    """Metres: seed cell size; must exceed the largest building so every cell holds ground."""
    outlier_depth: float = Field(2.0, gt=0.0, le=100.0)
    """Metres: a seed this far below the second-lowest point within ``outlier_radius``
    (and below the median of its seed neighbours) is a low outlier and is replaced."""
    outlier_radius: float = Field(3.0, gt=0.0, le=50.0)
    """Metres: neighbourhood radius of the low-outlier test."""
    max_rounds: int = Field(100, ge=1, le=10_000)
    """Upper bound on densification rounds (the filter normally stops earlier)."""
    min_spacing: float = Field(1.5, gt=0.0, le=50.0)
    """Metres: TIN vertices are drawn from the lowest point of each min_spacing
    cell, and facets smaller than min_spacing²/2 take no more; the final pass
    labels every other point. Bounds the TIN (and the cost) on dense clouds.
    At most 50 m: the isolated-low-point test of the candidates uses the same
    cell, and ``ground.lowpoints`` takes no larger one."""
    tail_fraction: float = Field(0.1, ge=0.0, le=1.0)
    """When a round grows the TIN by less than this share, one last round accepts
    every remaining point that passes the tests and the filter stops (0: run every
    one-per-facet round to the end). The tail otherwise costs a full
    re-triangulation per handful of points."""
    mirror_slope: float | None = Field(None, gt=0.0, le=90.0)
    """Degrees: a point failing the tests in a facet steeper than this is tested
    again by its mirror image through the facet's nearest vertex, against the
    facet the image falls in (after Axelsson 2000). At a convex break (a
    plateau's rim above a cliff, a tipped cliff's top) the facet under the point
    drops away, but the surface behind the vertex continues the point's own.
    Gentle facets never mirror. None: off (the default: on the ISPRS samples
    mirrors let roofs in); the conservative set of rotated runs uses it."""

    island_step: float | None = Field(2.5, gt=0.0, le=100.0)
    """Metres: a part of the ground TIN that meets the rest only across steps
    up of this height (steeper than ``island_slope``), away from the block's
    border, is an object (a roof seeded in a cell it fills) and is dropped
    before the final pass. None: off."""
    island_slope: float = Field(5.0, gt=0.0, lt=90.0)
    """Degrees: an edge of the TIN steeper than this, rising ``island_step`` or more, is a step.
    Low, because the TIN is not densified next to walls: a roof meets the ground
    by edges of 5-12 m at 25-35°, while terrain vertices 1.5-3 m apart rarely
    differ by ``island_step``."""
    low_candidates: bool = True
    """Candidates that are isolated low points of the cloud (the test of
    ``ground.lowpoints`` with its defaults: under two points below or within
    1 m above in a 6 m square) give way to the next lowest point of their
    cell. A return under the terrain is the lowest point of its cell, and in
    dense clouds (20 pts/m²) they are close enough to neighbour each other in
    the TIN, where the pit test below cannot see them (synthetic 20 pts/m²
    scene: Type I 24 % without, 0.06 % with)."""
    pit_depth: float | None = Field(0.3, gt=0.0, le=100.0)
    """Metres: a TIN vertex at least this far below every one of its TIN
    neighbours is a low outlier (a return under the terrain that a round took)
    and leaves the TIN before the next triangulation; left in, it tilts its
    facets down and the true ground around it fails the angle test (on the
    synthetic tile a few hundred such returns cost 2.4 % of the ground). A
    ditch or a valley floor has neighbours at its own height along it, and a
    real hollow's points are still judged by the final pass. None: off."""

    presets = {
        "conservative": {
            "terrain_angle": 75.0,
            "iteration_angle": 15.0,
            "iteration_distance": 1.0,
            "max_building_size": 10.0,
            "mirror_slope": 45.0,
        },
        "aggressive": {
            "terrain_angle": 88.0,
            "iteration_angle": 20.0,
            "iteration_distance": 1.2,
            "max_building_size": 10.0,
        },
    }

    def halo(self, density: float) -> float:
        """One seed cell: the lowest points that seed the TIN around a core
        point at the block's edge come from the cells next to it."""
        return float(self.max_building_size)


@register("ground.ptd", PtdParams, "progressive TIN densification", role="ground")
def classify_ground(
    xyz: NDArray[np.float64],
    params: PtdParams,
    *,
    sensor_origin: NDArray | None = None,
    seed_mask: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Boolean ground label per point of ``xyz`` (N×3, absolute coordinates).

    ``sensor_origin`` is accepted for a uniform ground-stage signature; the TIN
    filter does not use it. ``seed_mask`` marks points known to be ground (e.g.
    from another run): thinned to one per 2·``min_spacing`` cell they join the
    seeds, so densification starts from them too.
    """
    del sensor_origin
    xyz = np.asarray(xyz, dtype=np.float64)
    n = xyz.shape[0]
    ground = np.zeros(n, dtype=bool)
    if n < 3:
        return ground
    # Anchored origin: seed cells line up between neighbouring blocks.
    lo = xyz.min(axis=0)
    hi = xyz.max(axis=0)
    shift = np.r_[np.floor(lo[:2] / ANCHOR) * ANCHOR, lo[2]]
    local = xyz - shift
    box = (lo[:2] - shift[:2], hi[:2] - shift[:2])
    # Everything before the final pass works on the lowest point per
    # min_spacing cell: the TIN holds no more vertices than that anyway.
    if params.low_candidates:
        # A return under the terrain is the lowest of its cell: it gives way
        # to the next lowest (the final pass still judges it).
        lowpoint = LowPointParams(candidate_cell=params.min_spacing)
        keep = np.flatnonzero(~isolated_low_points(local, np.ones(n, dtype=bool), lowpoint))
        cand = keep[_lowest_per_cell(local[keep], params.min_spacing)]
    else:
        cand = _lowest_per_cell(local, params.min_spacing)
    cand_seeds, cand_excluded = _seeds(local[cand], params)
    seeds = cand[cand_seeds]
    excluded = np.zeros(n, dtype=bool)
    excluded[cand[cand_excluded]] = True
    if seed_mask is not None and np.any(seed_mask):
        known = np.flatnonzero(np.asarray(seed_mask, dtype=bool) & ~excluded)
        cell = 2.0 * params.min_spacing
        g = Grid.covering(local[known, 0], local[known, 1], cell)
        low = lowest_per_bin(g.index(local[known, 0], local[known, 1]), local[known, 2], g.size)
        seeds = np.union1d(seeds, known[low[low >= 0]])
    ground[seeds] = True
    if seeds.size < 3:
        return ground
    cand = cand[~excluded[cand]]
    frame = _frame(local[cand], local[seeds], box, params.max_building_size)
    _densify(local, ground, excluded, cand, frame, params)
    return ground


def _lowest_per_cell(local: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Index of the lowest point of every occupied ``cell``-sized cell (cells
    anchored on multiples of ``cell``), in cell order. Ties in z go to the smaller
    x, then y, so the choice does not depend on the order of the points."""
    grid = Grid.covering(local[:, 0], local[:, 1], cell)
    x, y = local[:, 0], local[:, 1]
    low = lowest_per_bin(grid.index(x, y), local[:, 2], grid.size, ties=(x, y))
    return low[low >= 0]


# --------------------------------------------------------------------- seeds


def _seeds(
    local: NDArray[np.float64], params: PtdParams
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Lowest point per cell of ``local`` (the candidates: lowest point per
    ``min_spacing`` cell), repeated after removing isolated low outliers.

    A seed is an outlier when it lies more than ``outlier_depth`` below (or
    5·``outlier_depth`` above) the median of its neighbours in the seed TIN *and* either below the
    second-lowest other point within ``outlier_radius`` by that much or alone
    within that radius: a lone point metres under its own surroundings, or a
    bird seeding an otherwise empty cell. A genuine valley bottom has ground points close around it and
    survives. Returns seed indices and a mask of excluded (outlier) points.
    """
    grid = Grid.covering(local[:, 0], local[:, 1], params.max_building_size)
    flat = grid.index(local[:, 0], local[:, 1])
    excluded = np.zeros(local.shape[0], dtype=bool)
    # One sort by (cell, z): a cell's seed is its first point not excluded.
    order = np.lexsort((local[:, 2], flat))
    starts = np.searchsorted(flat[order], np.arange(grid.size + 1))
    counts = starts[1:] - starts[:-1]
    occupied = np.flatnonzero(counts > 0)
    # The grid is anchored, not fitted to the data, so cells at the data's
    # edge can be slivers of a few points whose lowest may be a roof or
    # canopy point; they seed nothing (densification reaches them).
    full = occupied[counts[occupied] >= 0.2 * np.median(counts[occupied])]
    if full.size >= 4:
        occupied = full
    pos = starts[occupied].copy()
    for _ in range(8):
        seeds = order[pos]
        if seeds.size < 4:
            return seeds, excluded
        suspects = np.flatnonzero(_below_neighbours(local[seeds], params.outlier_depth))
        found = False
        for k in suspects:
            s = seeds[k]
            if _isolated_low(local, s, flat[s], grid, order, starts, excluded, params):
                excluded[s] = True
                found = True
                # Next point of the cell, unless the cell has no other.
                if pos[k] + 1 < starts[occupied[k] + 1]:
                    pos[k] += 1
        if not found:
            break
    seeds = order[pos]
    return seeds[~excluded[seeds]], excluded


def _below_neighbours(pts: NDArray[np.float64], depth: float) -> NDArray[np.bool_]:
    """Seeds more than ``depth`` below (or 5·``depth`` above) the median z of their TIN neighbours."""
    try:
        tri = Delaunay(pts[:, :2])
    except QhullError:
        return np.zeros(pts.shape[0], dtype=bool)
    indptr, nbrs = tri.vertex_neighbor_vertices
    counts = np.diff(indptr)
    owner = np.repeat(np.arange(pts.shape[0]), counts)
    zn = pts[nbrs, 2]
    o = np.lexsort((zn, owner))
    zs = zn[o]
    lo = indptr[:-1] + (counts - 1) // 2
    hi = indptr[:-1] + counts // 2
    ok = counts > 0
    med = np.full(pts.shape[0], np.inf)
    med[ok] = 0.5 * (zs[lo[ok]] + zs[hi[ok]])
    dev = pts[:, 2] - med
    # Low: any depth beyond the limit. High: only far up (birds), since a hill
    # top or a ridge in sparse data stands above its neighbours too.
    return (dev < -depth) | (dev > 5.0 * depth)


def _isolated_low(local, s, cell, grid, order, starts, excluded, params) -> bool:
    """Is point ``s`` more than ``outlier_depth`` below its near neighbours, or
    alone within ``outlier_radius`` (a bird, or a point far off the data)?"""
    iy, ix = divmod(int(cell), grid.nx)
    span = int(np.ceil(params.outlier_radius / grid.cell))
    idx = []
    for jy in range(max(iy - span, 0), min(iy + span, grid.ny - 1) + 1):
        a = jy * grid.nx + max(ix - span, 0)
        b = jy * grid.nx + min(ix + span, grid.nx - 1)
        idx.append(order[starts[a] : starts[b + 1]])
    cand = np.concatenate(idx)
    cand = cand[(cand != s) & ~excluded[cand]]
    d2 = ((local[cand, :2] - local[s, :2]) ** 2).sum(axis=1)
    near = np.sort(local[cand[d2 <= params.outlier_radius**2], 2])
    if near.size == 0:
        return True  # alone and far off its seed neighbours' height
    ref = near[1] if near.size > 1 else near[0]
    return bool(local[s, 2] < ref - params.outlier_depth)


def _frame(
    cand: NDArray[np.float64],
    seeds: NDArray[np.float64],
    box: tuple[NDArray[np.float64], NDArray[np.float64]],
    step: float,
) -> NDArray[np.float64]:
    """Virtual vertices around the bounding ``box`` of the points so every point falls in the TIN.

    Each takes the height of the lowest candidate (``cand``, the lowest point of
    each small cell) within a few metres of the border near it, so a slope is
    continued, not flattened to the nearest seed; or of its nearest seed where
    the border is empty. They are triangulated, never labelled.
    """
    lo = box[0] - 1.0
    hi = box[1] + 1.0
    nxs = max(int(np.ceil((hi[0] - lo[0]) / step)), 1)
    nys = max(int(np.ceil((hi[1] - lo[1]) / step)), 1)
    xs = np.linspace(lo[0], hi[0], nxs + 1)
    ys = np.linspace(lo[1], hi[1], nys + 1)
    border = np.concatenate(
        [
            np.column_stack([xs, np.full_like(xs, lo[1])]),
            np.column_stack([xs, np.full_like(xs, hi[1])]),
            np.column_stack([np.full_like(ys[1:-1], lo[0]), ys[1:-1]]),
            np.column_stack([np.full_like(ys[1:-1], hi[0]), ys[1:-1]]),
        ]
    )
    _, nearest = cKDTree(seeds[:, :2]).query(border)
    z = seeds[nearest, 2]
    margin = 2.0
    gap = np.minimum(cand[:, :2] - lo, hi - cand[:, :2]).min(axis=1)
    near = np.flatnonzero(gap < margin)
    if near.size:
        _, which = cKDTree(border).query(cand[near, :2])
        low = lowest_per_bin(which.astype(np.int64), cand[near, 2], border.shape[0])
        has = low >= 0
        z[has] = cand[near[low[has]], 2]
    return np.column_stack([border, z])


# ---------------------------------------------------------------- densify


def _refit_frame(verts: NDArray[np.float64], nf: int, nv: int, k: int = 8) -> None:
    """Continue the ground TIN to the frame: each frame vertex takes the height of
    the least-squares plane through its ``k`` nearest ground vertices, clamped to
    their height range widened by 2 m plus their distance (a 45° bound on the
    extrapolation), so slopes run on to the border."""
    g = verts[nf:nv]
    if g.shape[0] < max(k, 3):
        return
    f = verts[:nf]
    dist, idx = cKDTree(g[:, :2]).query(f[:, :2], k=k)
    nb = g[idx]  # (nf, k, 3)
    d = nb[:, :, :2] - f[:, None, :2]
    a = np.concatenate([np.ones((nf, k, 1)), d], axis=2)
    ata = np.einsum("nki,nkj->nij", a, a) + 1e-6 * np.eye(3)
    atz = np.einsum("nki,nk->ni", a, nb[:, :, 2])
    z = np.linalg.solve(ata, atz[..., None])[:, 0, 0]
    reach = 2.0 + dist[:, 0]
    lo = nb[:, :, 2].min(axis=1) - reach
    hi = nb[:, :, 2].max(axis=1) + reach
    verts[:nf, 2] = np.clip(z, lo, hi)


def _tin(verts: NDArray[np.float64]) -> Tin:
    """The current TIN through ``verts`` (local coordinates): startinpy's
    triangulation (Qhull for degenerate input) and the compiled walk of ``tin.py``."""
    return Tin(verts, origin=np.zeros(2))


def _judge(
    tin: Tin, pts: NDArray[np.float64], params: PtdParams, scores: bool
) -> tuple[NDArray, NDArray, NDArray]:
    """Facet of each point (-1 outside the TIN) and the acceptance test against it.

    Returns (facet, ok, sin of the angle). The angle is only worked out where
    it decides the test (``scores``: for every point that passes otherwise):
    within a metre of a vertex, scanner noise alone makes steep angles, so a
    point is judged as if a metre away, and a point closer to the facet than
    sin(iteration_angle) metres passes the angle test wherever it is.
    """
    s = tin.facet_of(pts[:, :2])
    nz = tin.facet_planes().nz
    inside = np.flatnonzero(s >= 0)
    si, pi = s[inside], pts[inside]
    dist = tin.plane_distance(si, pi)
    sin_max = np.sin(np.radians(params.iteration_angle))
    cos_max = np.cos(np.radians(params.terrain_angle))
    ok = (dist < params.iteration_distance) & (nz[si] >= cos_max)
    sin_angle = np.full(inside.size, np.inf)
    need = np.flatnonzero(ok & (scores | (dist >= sin_max)))
    if need.size:
        rmin, _ = tin.nearest_corner(si[need], pi[need])
        sin_angle[need] = dist[need] / np.maximum(rmin, 1.0)
    easy = ok.copy()
    easy[need] = False
    sin_angle[easy] = dist[easy]  # below sin_max: passes
    ok &= sin_angle < sin_max
    if params.mirror_slope is not None and not ok.all():
        # Mirror image p' = 2v - p through the nearest vertex v, judged against
        # the facet p' falls in: the surface behind v, continued past it.
        bad = np.flatnonzero(~ok & (nz[si] < np.cos(np.radians(params.mirror_slope))))
        if bad.size:
            _, v = tin.nearest_corner(si[bad], pi[bad])
            img = 2.0 * v - pi[bad]
            s2 = tin.facet_of(img[:, :2])
            has = np.flatnonzero(s2 >= 0)
            bad, img, s2 = bad[has], img[has], s2[has]
            d2 = tin.plane_distance(s2, img)
            r2, _ = tin.nearest_corner(s2, img)
            sin2 = d2 / np.maximum(r2, 1.0)
            ok2 = (d2 < params.iteration_distance) & (sin2 < sin_max) & (nz[s2] >= cos_max)
            ok[bad[ok2]] = True
            sin_angle[bad[ok2]] = sin2[ok2]
    facet = np.full(pts.shape[0], -1, dtype=np.int64)
    facet[inside] = si
    full_ok = np.zeros(pts.shape[0], dtype=bool)
    full_ok[inside] = ok
    full_sin = np.full(pts.shape[0], np.inf)
    full_sin[inside] = sin_angle
    return facet, full_ok, full_sin


def _densify(
    local: NDArray[np.float64],
    ground: NDArray[np.bool_],
    excluded: NDArray[np.bool_],
    cand: NDArray[np.int64],
    frame: NDArray[np.float64],
    params: PtdParams,
) -> None:
    """Grow ``ground`` in place by rounds of TIN densification.

    Rounds insert candidates only (``cand``: the lowest point of each
    ``min_spacing`` cell), one per facet per round, while facets are larger
    than ``min_spacing``²/2 and rounds still grow the TIN by ``tail_fraction``;
    then one last pass accepts every remaining point that passes against the
    final TIN without inserting it. Delaunay is the cost, so the TIN stays
    near one vertex per ``min_spacing``² however dense the cloud, and each
    round judges one point per cell, not the cloud.
    """
    nf = frame.shape[0]
    seeds = np.flatnonzero(ground)
    pending = cand[~ground[cand]]
    verts = np.empty((nf + seeds.size + pending.size, 3))
    verts[:nf] = frame
    verts[nf : nf + seeds.size] = local[seeds]
    nv = nf + seeds.size
    vid = np.full(verts.shape[0], -1, dtype=np.int64)  # point index of each vertex
    vid[nf:nv] = seeds
    area_min = 0.5 * params.min_spacing**2

    tin = None
    for _ in range(params.max_rounds):
        _refit_frame(verts, nf, nv)
        try:
            tin = _tin(verts[:nv])
        except QhullError:
            return
        if pending.size == 0:
            break
        s, ok, score = _judge(tin, local[pending], params, scores=True)
        pick = np.flatnonzero(ok & (tin.facet_planes().area[np.maximum(s, 0)] >= area_min))
        if pick.size == 0:
            break
        o = pick[np.lexsort((score[pick], s[pick]))]
        first = np.r_[True, s[o][1:] != s[o][:-1]]
        chosen = o[first]
        new = pending[chosen]
        if params.pit_depth is not None:
            # Low outliers of this TIN leave before the next triangulation.
            pits = _pits(tin, nf, params.pit_depth)
            if pits.any():
                ground[vid[:nv][pits]] = False
                kept = np.flatnonzero(~pits)
                verts[: kept.size], vid[: kept.size] = verts[kept], vid[kept]
                nv = kept.size
        ground[new] = True
        verts[nv : nv + new.size] = local[new]
        vid[nv : nv + new.size] = new
        nv += new.size
        keep = np.ones(pending.size, dtype=bool)
        keep[chosen] = False
        pending = pending[keep]
        if chosen.size < params.tail_fraction * nv:
            _refit_frame(verts, nf, nv)
            try:
                tin = _tin(verts[:nv])
            except QhullError:
                return
            break
    # Low outliers and raised islands leave the final TIN before the final pass.
    if tin is not None and (params.island_step is not None or params.pit_depth is not None):
        drop = np.zeros(nv, dtype=bool)
        if params.pit_depth is not None:
            drop |= _pits(tin, nf, params.pit_depth)
        if params.island_step is not None:
            drop |= _islands(tin, nf, params.island_step, params.island_slope)
        if drop.any():
            ground[vid[:nv][drop]] = False
            verts = verts[:nv][~drop]
            _refit_frame(verts, nf, verts.shape[0])
            try:
                tin = _tin(verts)
            except QhullError:
                return
    # Final pass: every other point judged against the last TIN, none inserted.
    if tin is not None:
        rest = np.flatnonzero(~ground & ~excluded)
        if rest.size:
            rest = rest[spatial_order(local[rest, :2], 8.0)]
            _, ok, _ = _judge(tin, local[rest], params, scores=False)
            ground[rest[ok]] = True


def _pits(tin: Tin, nf: int, depth: float) -> NDArray[np.bool_]:
    """TIN vertices (not of the frame) at least ``depth`` below every TIN
    neighbour that is not a frame vertex."""
    verts = tin.local_xyz
    nv = verts.shape[0]
    simp = tin.simplices
    a = np.concatenate([simp[:, 0], simp[:, 1], simp[:, 2], simp[:, 1], simp[:, 2], simp[:, 0]])
    b = np.concatenate([simp[:, 1], simp[:, 2], simp[:, 0], simp[:, 0], simp[:, 1], simp[:, 2]])
    real = b >= nf
    lowest_neighbour = np.full(nv, np.inf)
    np.minimum.at(lowest_neighbour, a[real], verts[b[real], 2])
    pit = (verts[:, 2] + depth <= lowest_neighbour) & np.isfinite(lowest_neighbour)
    pit[:nf] = False
    return pit


def _islands(tin: Tin, nf: int, step: float, slope: float) -> NDArray[np.bool_]:
    """TIN vertices of raised islands: parts of the ground TIN that only meet
    the rest across downward steps (edges rising at least ``step`` metres at
    more than ``slope`` degrees), nowhere the block's border, and are not its
    largest part. A roof seeded in a cell it fills is such an island; terrain
    joins its surroundings somewhere without a step. Repeated so a roof under
    a raised part (a tower) goes too."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v = tin.local_xyz
    nv = v.shape[0]
    simp = tin.simplices
    e = np.concatenate([simp[:, [0, 1]], simp[:, [1, 2]], simp[:, [2, 0]]])
    dz = v[e[:, 1], 2] - v[e[:, 0], 2]
    h = np.hypot(v[e[:, 1], 0] - v[e[:, 0], 0], v[e[:, 1], 1] - v[e[:, 0], 1])
    is_step = (np.abs(dz) >= step) & (np.abs(dz) >= np.tan(np.radians(slope)) * h)
    to_frame = (e < nf).any(axis=1)
    gentle = ~is_step & ~to_frame
    g = coo_matrix(
        (np.ones(np.count_nonzero(gentle)), (e[gentle, 0], e[gentle, 1])), shape=(nv, nv)
    )
    ncomp, comp = connected_components(g, directed=False)
    size = np.bincount(comp[nf:], minlength=ncomp)
    fixed = np.zeros(ncomp, dtype=bool)
    fixed[comp[:nf]] = True  # frame vertices: one component each
    fixed[np.argmax(size)] = True
    fe = e[to_frame]
    fixed[comp[np.where(fe[:, 0] < nf, fe[:, 1], fe[:, 0])]] = True
    se = e[is_step & ~to_frame]
    lo = np.where(v[se[:, 0], 2] < v[se[:, 1], 2], se[:, 0], se[:, 1])
    hi = np.where(v[se[:, 0], 2] < v[se[:, 1], 2], se[:, 1], se[:, 0])
    cross = comp[lo] != comp[hi]
    lo, hi = comp[lo[cross]], comp[hi[cross]]
    gone = np.zeros(ncomp, dtype=bool)
    for _ in range(4):
        live = ~gone[lo] & ~gone[hi]
        below = np.zeros(ncomp, dtype=bool)
        below[lo[live]] = True  # the lower side of a step: something stands on it
        island = ~fixed & ~gone & ~below & (size > 0)
        if not island.any():
            break
        gone |= island
    drop = gone[comp]
    drop[:nf] = False
    return drop
