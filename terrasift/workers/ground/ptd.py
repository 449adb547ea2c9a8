"""Ground by progressive TIN densification (DESIGN §5.2; the TerraScan-style
filter of the rotation seed, after Axelsson 2000).

Seeds are the lowest point of every ``max_building_size`` cell, with isolated
low outliers removed. A TIN through the seeds is then densified in rounds: a
point is accepted when its perpendicular distance to the facet it falls in is
below ``iteration_distance`` and its angles to the facet's vertices are below
``iteration_angle``; facets steeper than ``terrain_angle`` take no points. Each
round re-triangulates and accepts at most one point per facet (the one with the
smallest angle), so a facet's estimate never jumps by more than one point; it
stops when a round adds nothing.

Speed: every round is a handful of vectorised passes. Points are visited in a
spatially coherent order (``find_simplex`` walks from the previous hit), and a
point whose facet survived the re-triangulation unchanged is not tested again,
since its verdict cannot have changed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import Delaunay, QhullError

from terrasift.workers.bins import Grid, anchored_origin, lowest_per_bin
from terrasift.workers.registry import StageParams, register
from terrasift.workers.surface import with_transform


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
    min_spacing: float = Field(1.5, gt=0.0, le=100.0)
    """Metres: facets smaller than min_spacing²/2 take no more TIN vertices; the
    final pass labels the points in them. Bounds the TIN (and the cost) on dense clouds."""
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


@register("ground.ptd", PtdParams, "progressive TIN densification")
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
    local = xyz - np.r_[anchored_origin(xyz), xyz[:, 2].min()]
    seeds, excluded = _seeds(local, params)
    if seed_mask is not None and np.any(seed_mask):
        known = np.flatnonzero(np.asarray(seed_mask, dtype=bool) & ~excluded)
        cell = 2.0 * params.min_spacing
        g = Grid.covering(local[known, 0], local[known, 1], cell)
        low = lowest_per_bin(g.index(local[known, 0], local[known, 1]), local[known, 2], g.size)
        seeds = np.union1d(seeds, known[low[low >= 0]])
    if seeds.size < 3:
        ground[seeds] = True
        return ground
    ground[seeds] = True
    frame = _frame(local, seeds, excluded, params.max_building_size)
    _densify(local, ground, excluded, frame, params)
    return ground


# --------------------------------------------------------------------- seeds


def _seeds(local: NDArray[np.float64], params: PtdParams) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Lowest point per cell, repeated after removing isolated low outliers.

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
    local: NDArray[np.float64], seeds: NDArray[np.int64], excluded: NDArray[np.bool_], step: float
) -> NDArray[np.float64]:
    """Virtual vertices around the bounding box so every point falls in the TIN.

    Each takes the height of the lowest point within a few metres of the border
    near it (so a slope is continued, not flattened to the nearest seed), or of
    its nearest seed where the border is empty. They are triangulated, never labelled.
    """
    from scipy.spatial import cKDTree

    lo = local[:, :2].min(axis=0) - 1.0
    hi = local[:, :2].max(axis=0) + 1.0
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
    _, nearest = cKDTree(local[seeds, :2]).query(border)
    z = local[seeds[nearest], 2]
    margin = 2.0
    gap = np.minimum(local[:, :2] - lo, hi - local[:, :2]).min(axis=1)
    near = np.flatnonzero((gap < margin) & ~excluded)
    if near.size:
        _, which = cKDTree(border).query(local[near, :2])
        low = lowest_per_bin(which.astype(np.int64), local[near, 2], border.shape[0])
        has = low >= 0
        z[has] = local[near[low[has]], 2]
    return np.column_stack([border, z])


# ---------------------------------------------------------------- densify


def _spatial_order(xy: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Row-major order of ``cell``-sized bins, serpentine, so consecutive points are close."""
    ix = np.floor(xy[:, 0] / cell).astype(np.int64)
    iy = np.floor(xy[:, 1] / cell).astype(np.int64)
    nx = int(ix.max()) + 1
    ix = np.where(iy % 2 == 1, nx - 1 - ix, ix)
    return np.argsort(iy * nx + ix, kind="stable")


def _facet_keys(simplices: NDArray, base: int) -> NDArray:
    """One comparable key per facet from its sorted vertex ids (stable across rounds)."""
    s = np.sort(simplices, axis=1).astype(np.int64)
    if base < 2_000_000:
        return (s[:, 0] * base + s[:, 1]) * base + s[:, 2]
    return np.ascontiguousarray(s).view(np.dtype((np.void, 24))).ravel()


def _refit_frame(verts: NDArray[np.float64], nf: int, nv: int, k: int = 8) -> None:
    """Continue the ground TIN to the frame: each frame vertex takes the height of
    the least-squares plane through its ``k`` nearest ground vertices, clamped to
    their height range widened by 2 m plus their distance (a 45° bound on the
    extrapolation), so slopes run on to the border."""
    from scipy.spatial import cKDTree

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


def _judge(
    tri: Delaunay, verts: NDArray[np.float64], pts: NDArray[np.float64], params: PtdParams
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Facet of each point and the acceptance test against it.

    Returns (inside, facet, ok, sin of the angle, facet horizontal area), the
    last four for the points inside the TIN only.
    """
    simp = tri.simplices
    s = tri.find_simplex(pts[:, :2])
    inside = s >= 0
    s, pts = s[inside], pts[inside]
    a = verts[simp[s, 0]]
    b = verts[simp[s, 1]]
    c = verts[simp[s, 2]]
    normal = np.cross(b - a, c - a)
    area = 0.5 * np.abs(normal[:, 2])
    norm = np.linalg.norm(normal, axis=1)
    norm[norm == 0] = np.inf
    nz = np.abs(normal[:, 2]) / norm
    dist = np.abs(np.einsum("ij,ij->i", pts - a, normal)) / norm
    rmin = np.sqrt(
        np.minimum(
            np.minimum(((pts - a) ** 2).sum(1), ((pts - b) ** 2).sum(1)),
            ((pts - c) ** 2).sum(1),
        )
    )
    # Within a metre of a vertex, scanner noise alone makes steep angles:
    # judge such points as if a metre away.
    sin_angle = dist / np.maximum(rmin, 1.0)
    sin_max = np.sin(np.radians(params.iteration_angle))
    cos_max = np.cos(np.radians(params.terrain_angle))
    ok = (dist < params.iteration_distance) & (sin_angle < sin_max) & (nz >= cos_max)
    if params.mirror_slope is not None and not ok.all():
        # Mirror image p' = 2v - p through the nearest vertex v, judged against
        # the facet p' falls in: the surface behind v, continued past it.
        bad = np.flatnonzero(~ok & (nz < np.cos(np.radians(params.mirror_slope))))
        pb = pts[bad]
        vs = np.stack([a[bad], b[bad], c[bad]], axis=1)
        near = np.argmin(((vs - pb[:, None, :]) ** 2).sum(axis=2), axis=1)
        img = 2.0 * vs[np.arange(bad.size), near] - pb
        s2 = tri.find_simplex(img[:, :2])
        has = np.flatnonzero(s2 >= 0)
        bad, img, s2 = bad[has], img[has], s2[has]
        a2 = verts[simp[s2, 0]]
        b2 = verts[simp[s2, 1]]
        c2 = verts[simp[s2, 2]]
        n2 = np.cross(b2 - a2, c2 - a2)
        norm2 = np.linalg.norm(n2, axis=1)
        norm2[norm2 == 0] = np.inf
        d2 = np.abs(np.einsum("ij,ij->i", img - a2, n2)) / norm2
        r2 = np.sqrt(
            np.minimum(
                np.minimum(((img - a2) ** 2).sum(1), ((img - b2) ** 2).sum(1)),
                ((img - c2) ** 2).sum(1),
            )
        )
        sin2 = d2 / np.maximum(r2, 1.0)
        ok2 = (d2 < params.iteration_distance) & (sin2 < sin_max) & (np.abs(n2[:, 2]) / norm2 >= cos_max)
        ok[bad[ok2]] = True
        sin_angle[bad[ok2]] = sin2[ok2]
    return inside, s, ok, sin_angle, area


def _densify(
    local: NDArray[np.float64],
    ground: NDArray[np.bool_],
    excluded: NDArray[np.bool_],
    frame: NDArray[np.float64],
    params: PtdParams,
) -> None:
    """Grow ``ground`` in place by rounds of TIN densification.

    One point per facet per round while facets are larger than
    ``min_spacing``²/2 and rounds still grow the TIN by ``tail_fraction``; then
    one last pass accepts every pending point that passes against the final
    TIN without inserting it. Delaunay is the cost, so the TIN stays near one
    vertex per ``min_spacing``² however dense the cloud.
    """
    n = local.shape[0]
    nf = frame.shape[0]
    seeds = np.flatnonzero(ground)
    verts = np.empty((nf + n, 3))
    verts[:nf] = frame
    verts[nf : nf + seeds.size] = local[seeds]
    nv = nf + seeds.size
    base = nf + n
    area_min = 0.5 * params.min_spacing**2

    pending = np.flatnonzero(~ground & ~excluded)
    spacing = max(np.sqrt((np.ptp(local[:, 0]) * np.ptp(local[:, 1]) + 1.0) / n), 0.1)
    pending = pending[_spatial_order(local[pending, :2], 8.0 * spacing)]
    last_key: NDArray | None = None

    def accept(chosen: NDArray[np.int64], insert: bool) -> None:
        nonlocal pending, last_key, nv
        new = pending[chosen]
        ground[new] = True
        if insert:
            verts[nv : nv + new.size] = local[new]
            nv += new.size
        keep = np.ones(pending.size, dtype=bool)
        keep[chosen] = False
        pending = pending[keep]
        if last_key is not None:
            last_key = last_key[keep]

    tri = None
    for _ in range(params.max_rounds):
        if pending.size == 0:
            return
        _refit_frame(verts, nf, nv)
        try:
            tri = with_transform(Delaunay(verts[:nv, :2]))
        except QhullError:
            return
        keys = _facet_keys(tri.simplices, base)
        # A point whose facet survived re-triangulation keeps its verdict.
        ti = np.flatnonzero(~np.isin(last_key, keys)) if last_key is not None else np.arange(pending.size)
        inside, s, ok, score, area = _judge(tri, verts, local[pending[ti]], params)
        ti = ti[inside]
        if last_key is None:
            last_key = np.zeros(pending.size, dtype=keys.dtype)
        last_key[ti] = keys[s]
        pick = ok & (area >= area_min)
        if not pick.any():
            break
        cand = np.flatnonzero(pick)
        o = cand[np.lexsort((score[cand], s[cand]))]
        first = np.r_[True, s[o][1:] != s[o][:-1]]
        chosen = ti[o[first]]
        accept(chosen, insert=True)
        if chosen.size < params.tail_fraction * nv:
            try:
                tri = with_transform(Delaunay(verts[:nv, :2]))
            except QhullError:
                return
            break
    # Final pass: every pending point judged against the last TIN, none inserted.
    if tri is not None and pending.size:
        inside, s, ok, score, area = _judge(tri, verts, local[pending], params)
        accept(np.flatnonzero(inside)[ok], insert=False)
