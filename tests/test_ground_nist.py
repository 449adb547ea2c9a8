"""ground.nist: each procedure against exact synthetic truth, plus real data when present."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError, cKDTree

from terrasift.errors import ParameterError
from terrasift.metrics import ground_score
from terrasift.synthetic import rural, slopes
from terrasift.synthetic.terrain import Surface, make_scene
from terrasift.workers.bins import Grid, cell_order
from terrasift.workers.ground import nist
from terrasift.workers.ground import tin as tin_module
from terrasift.workers.ground.concentric import ConcentricGrid, ring_ratio
from terrasift.workers.ground.growth import grow_ground
from terrasift.workers.ground.masking import mask_points, partial_tin
from terrasift.workers.ground.nodes import square_lowest
from terrasift.workers.ground.raised import raised_segments, tin_edges
from terrasift.workers.ground.support import supported_points
from terrasift.workers.ground.tin import (
    ABOVE,
    BELOW,
    IN_BAND,
    Mesh,
    Tin,
    _transforms,
    delaunay,
    hilbert_key,
    screen,
)
from terrasift.workers.registry import get_stage


def test_tin_matches_linear_interpolation_and_locates_like_qhull():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 100, (2000, 2)) + [5e5, 5.4e6], rng.normal(0, 3, 2000)])
    tin = Tin(pts)
    q = rng.uniform(-5, 105, (5000, 2)) + [5e5, 5.4e6] - tin.origin
    t, _ = tin.locate(q)
    qhull = Delaunay(tin.xy)
    ref = qhull.find_simplex(q)
    assert np.array_equal(ref >= 0, t >= 0)
    inside = ref >= 0
    same = np.sort(tin.tri.simplices[t[inside]], axis=1) == np.sort(
        qhull.simplices[ref[inside]], axis=1
    )
    assert same.all()
    # A plane is reproduced exactly inside the hull.
    plane = Tin(
        np.column_stack([pts[:, :2], 2.0 + 0.3 * (pts[:, 0] - 5e5) - 0.1 * (pts[:, 1] - 5.4e6)])
    )
    inside = ref >= 0
    z = plane.at_local(q[inside])
    xy = q[inside] + plane.origin
    assert np.allclose(z, 2.0 + 0.3 * (xy[:, 0] - 5e5) - 0.1 * (xy[:, 1] - 5.4e6), atol=1e-6)


def _triangle_set(simplices: NDArray) -> set[tuple[int, ...]]:
    return {tuple(t) for t in np.sort(np.asarray(simplices), axis=1).tolist()}


def _neighbour_sets(tri) -> dict[tuple[int, ...], set[tuple[int, ...]]]:
    s = np.sort(np.asarray(tri.simplices), axis=1)
    nb = np.asarray(tri.neighbors)
    return {tuple(s[i]): {tuple(s[j]) for j in nb[i] if j >= 0} for i in range(s.shape[0])}


def test_delaunay_equals_qhull_with_neighbours_and_hull():
    rng = np.random.default_rng(7)
    xy = rng.uniform(-50, 50, (3000, 2))
    mesh, qhull = delaunay(xy), Delaunay(xy)
    assert isinstance(mesh, Mesh)
    assert _triangle_set(mesh.simplices) == _triangle_set(qhull.simplices)
    assert _neighbour_sets(mesh) == _neighbour_sets(qhull)
    assert _triangle_set(mesh.convex_hull) == _triangle_set(qhull.convex_hull)
    ptr, idx = mesh.vertex_neighbor_vertices
    qptr, qidx = qhull.vertex_neighbor_vertices
    for v in range(0, 3000, 97):
        assert set(idx[ptr[v] : ptr[v + 1]]) == set(qidx[qptr[v] : qptr[v + 1]])


def test_delaunay_keeps_the_first_of_coincident_points_and_rejects_collinear():
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 10, (500, 2))
    copied = np.r_[np.arange(50), np.arange(100, 120)]
    pts = np.concatenate([xy[copied], xy])  # copies first: they are the vertices
    mesh = delaunay(pts)
    s = np.asarray(mesh.simplices)
    assert not np.isin(s, 70 + copied).any()  # later points at a taken position are in no triangle
    as_xy = np.r_[copied, np.arange(500)][s]  # row of ``xy`` of each corner
    assert _triangle_set(as_xy) == _triangle_set(Delaunay(xy).simplices)
    ptr, _ = mesh.vertex_neighbor_vertices
    assert (np.diff(ptr)[70 + copied] == 0).all()
    assert np.array_equal(
        delaunay(pts, coincident=True).simplices, s
    )  # sorted out first: same mesh
    line = np.column_stack([np.arange(10.0), 2.0 * np.arange(10.0)])
    with pytest.raises(QhullError):
        delaunay(line)


def test_screen_removes_spikes_and_pits_but_keeps_a_slope():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 100, (1500, 2))
    z = 0.8 * xy[:, 0]  # 39° slope
    spikes = rng.choice(1500, 20, replace=False)
    pits = rng.choice(np.setdiff1d(np.arange(1500), spikes), 20, replace=False)
    z[spikes] += 5.0
    z[pits] -= 5.0
    pts = np.column_stack([xy, z])
    slopes_ = np.tile([0.8, 0.0], (1500, 1))
    keep, tin = screen(pts, 0.5, 1.0, slopes=slopes_)
    assert tin is not None and tin.n_vertices == keep.size
    gone = np.setdiff1d(np.arange(1500), keep)
    assert set(spikes) | set(pits) <= set(gone)
    assert gone.size <= 60  # nearly no genuine slope vertex deleted


def test_masking_marks_trees_not_open_ground():
    sc = make_scene(
        120, 4, n_buildings=0, tree_density=0.003, bush_density=0.0, outlier_rate=0, seed=3
    )
    idx = mask_points(sc.xyz, 0.12, edge=2.5 / 2)
    assert idx.size > 0
    # Mask points sit under or in crowns: a vegetation point is within 1 m.
    veg = cKDTree(sc.xyz[sc.truth != 2, :2])
    near = lambda i: np.isfinite(veg.query(sc.xyz[i, :2], distance_upper_bound=1.0)[0])  # noqa: E731
    base = near(np.arange(len(sc))).mean()
    assert near(idx).mean() > 2 * base
    _, verts = partial_tin(sc.xyz, 0.1, "area")
    assert abs(verts.size - round(0.1 * len(sc))) <= 1


def test_concentric_grid_has_perpendicular_diagonals():
    g = ConcentricGrid.build(10.0, 20.0, 2.0, 50.0, 5.0)
    step = g.step
    r1, r2 = g.radii[0], g.radii[1]
    assert np.isclose(r2 / r1, ring_ratio(step))
    # Corners of a sector: (r1, 0), (r1, Δ), (r2, 0), (r2, Δ); diagonals must be perpendicular.
    a = np.array([r1, 0.0]), np.array([r2 * np.cos(step), r2 * np.sin(step)])
    b = np.array([r1 * np.cos(step), r1 * np.sin(step)]), np.array([r2, 0.0])
    assert abs(np.dot(a[1] - a[0], b[1] - b[0])) < 1e-9
    assert g.radii[-1] == 50.0 and g.radii[-1] / g.radii[-2] >= ring_ratio(
        step
    )  # last ring extended
    x = np.array([10.0, 13.0, 10.0 + 49.9, 10 + 60.0])
    y = np.array([20.0, 20.1, 20.0, 20.0])
    ring = int(np.floor(np.log(np.hypot(3.0, 0.1) / 2.0) / np.log(ring_ratio(step))))
    assert list(g.index(x, y)) == [0, 1 + ring * g.n_sectors, 1 + (g.n_rings - 1) * g.n_sectors, -1]
    cx, cy = g.centers()
    assert g.index(cx, cy).tolist() == list(range(g.size))


def test_select_reject_reasons_and_plane_fit():
    sc = slopes.steep_hillside(60, 8, seed=4)
    grid = Grid.covering(sc.xyz[:, 0], sc.xyz[:, 1], 4.0)
    none = np.zeros((0, 2))
    level = nist.select_reject(
        sc.xyz, nist.NistParams(bin_fit="level", z_tol=0.5), grid, mask_xy=none
    )
    plane = nist.select_reject(
        sc.xyz, nist.NistParams(bin_fit="plane", z_tol=0.5), grid, mask_xy=none
    )
    # On a 40° slope a 4 m bin spans ~1 m RMS about its mean: level rejects, the plane accepts.
    assert np.mean(level.reason[level.stats.n > 0] == nist.RMS) > 0.9
    assert plane.accepted[plane.stats.n >= 3].mean() > 0.9
    # Candidates are ground, or low outliers (which screening removes later).
    cand = plane.candidates
    below = sc.xyz[cand, 2] < sc.surface(sc.xyz[cand, 0], sc.xyz[cand, 1]) - 0.5
    assert np.all(sc.is_ground[cand] | ((sc.truth[cand] == 7) & below))
    masked = nist.select_reject(sc.xyz, nist.NistParams(), grid, mask_xy=sc.xyz[:5, :2])
    assert (masked.reason == nist.MASK).sum() >= 1
    assert masked.stats.n.sum() == len(sc)


@pytest.mark.parametrize("density", [1.0, 8.0])
def test_classify_ground_on_synthetic_scene(density):
    sc = make_scene(150, density, seed=7)
    g = nist.classify_ground(sc.xyz, nist.NistParams())
    s = ground_score(sc.is_ground, g)
    assert s.kappa > 0.85, s
    depth = sc.surface(sc.xyz[:, 0], sc.xyz[:, 1]) - sc.xyz[:, 2]
    assert not g[(sc.truth == 7) & (depth > 2.0)].any()  # low outliers deeper than the tolerance


def test_plane_fit_helps_on_steep_hillside():
    sc = slopes.steep_hillside(100, 4, seed=8)
    plane = ground_score(
        sc.is_ground, nist.classify_ground(sc.xyz, nist.NistParams(bin_fit="plane"))
    )
    assert plane.type1 < 0.03, plane


def test_concentric_path_with_sensor_origin():
    rng = np.random.default_rng(9)
    # A ground-based scan: density falls with range around the sensor.
    r = 40 * rng.random(60000) ** 2 + 0.5
    a = rng.uniform(0, 2 * np.pi, r.size)
    x, y = 100 + r * np.cos(a), 200 + r * np.sin(a)
    surf = Surface(z0=10, gx=0.1, gy=0.05, waves=((0.5, 30.0, 30.0, 0.0),))
    z = surf(x, y) + rng.normal(0, 0.02, r.size)
    bush = rng.random(r.size) < 0.2
    z[bush] += rng.uniform(0.6, 2.0, bush.sum())
    xyz = np.column_stack([x, y, z])
    g = nist.classify_ground(xyz, nist.NistParams(), sensor_origin=np.array([100.0, 200.0, 11.5]))
    s = ground_score(~bush, g)
    assert s.kappa > 0.9, s
    with pytest.raises(ValueError):
        nist.classify_ground(xyz, nist.NistParams(grid="concentric"))


def test_params_registry_and_presets():
    stage = get_stage("ground.nist")
    assert stage.run is nist.classify_ground
    assert (
        nist.NistParams.preset("conservative").ground_tol
        < nist.NistParams.preset("aggressive").ground_tol
    )
    with pytest.raises(ParameterError):
        nist.NistParams.preset("default", mask_fraction=0.9)


def test_collinear_block_does_not_raise():
    xyz = np.column_stack([np.linspace(0, 10, 50) + 5e5, np.full(50, 5.4e6), np.zeros(50)])
    assert nist.classify_ground(xyz, nist.NistParams()).shape == (50,)


def _grid_nodes(size: float, step: float, seed: int) -> NDArray:
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, size, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(0, 0.8 * step, (g.size**2, 2))
    return xy


def test_growth_climbs_a_ridge_but_not_a_roof():
    xy = _grid_nodes(120, 2.0, 11)
    # A ridge 10 m high with 30° flanks along y, and a 6 m roof on flat ground.
    ridge = np.clip(10.0 - np.tan(np.radians(30)) * np.abs(xy[:, 0] - 40.0), 0.0, None)
    roof = (np.abs(xy[:, 0] - 95.0) < 10) & (np.abs(xy[:, 1] - 60.0) < 10)
    z = ridge + 6.0 * roof
    xyz = np.column_stack([xy, z])
    seed = (z < 3.0) & ~roof  # a surface that cut the ridge at 3 m and never saw the roof
    ground = grow_ground(xyz, seed, tol=0.3, bend_deg=7.0, max_rise=3.0)
    assert ground[~roof].all()
    assert not ground[roof].any()


def test_raised_segments_drop_a_roof_and_keep_a_steep_hill():
    xy = _grid_nodes(120, 2.0, 12)
    r = np.hypot(xy[:, 0] - 40.0, xy[:, 1] - 60.0)
    hill = np.clip(12.0 - np.tan(np.radians(40)) * r, 0.0, None)  # a 40° cone
    roof = (np.abs(xy[:, 0] - 95.0) < 10) & (np.abs(xy[:, 1] - 60.0) < 10)
    tower = (np.abs(xy[:, 0] - 97.0) < 3) & (np.abs(xy[:, 1] - 60.0) < 3)
    z = hill + 5.0 * roof + 8.0 * tower
    xyz = np.column_stack([xy, z])
    drop = raised_segments(xyz, Delaunay(xy), 2.0, 10.0)
    assert np.array_equal(drop, roof)


def test_raised_segments_keep_an_embankment_whose_sides_carry_returns():
    # A crest 8 x 32 m, 2.5 m high, on level ground; the TIN's vertices (a 4 m grid)
    # fall on the crest and the foot only, so its sides are steps, as on sparse data.
    # The returns (0.1-1 per m²) lie on the sloped sides of the embankment and
    # nowhere between the foot and the top of a platform's walls.
    def surface(x, y, walled):
        d = np.maximum(np.abs(x - 40.0) - 4.0, np.abs(y - 40.0) - 16.0)
        return np.where(d <= 0, 2.5, 0.0) if walled else 2.5 * np.clip(1 - d / 4, 0, 1)

    g = np.arange(0.0, 80.1, 4.0)
    vx, vy = (a.ravel() for a in np.meshgrid(g, g))
    rng = np.random.default_rng(3)
    for n in (640, 6400):
        pxy = rng.uniform(0, 80, (n, 2))
        for walled in (False, True):
            xyz = np.column_stack([vx, vy, surface(vx, vy, walled)])
            pts = np.column_stack([pxy, surface(pxy[:, 0], pxy[:, 1], walled)])
            tri = Delaunay(xyz[:, :2])
            crest = xyz[:, 2] > 2.4
            assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, walls=0.5), crest)
            drop = raised_segments(xyz, tri, 0.3, 10.0, walls=0.5, sides=0.5, points=pts)
            assert np.array_equal(drop, crest if walled else np.zeros_like(crest))


def test_raised_segments_drop_a_roof_cut_into_a_slope_but_not_a_bench():
    # A 45° hillside (z = y) on a 2 m grid of odd coordinates, so every node
    # misses an integer level by 1 m or more; two diamonds (squares turned 45°
    # to the slope), both stepped off the hill all round.
    rng = np.random.default_rng(15)
    g = np.arange(1.0, 100.0, 2.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.1, 0.1, (g.size**2, 2))
    z = xy[:, 1].copy()
    # A bench cut into the slope at the hill's height at its centre: cut above,
    # fill below; the lower side of as many steps as it is the upper side of.
    bench = np.abs(xy[:, 0] - 25.0) + np.abs(xy[:, 1] - 50.0) < 14.0
    # A flat roof 8 m above the hill at its centre: the hill rises above it
    # only round its uphill corner.
    roof = np.abs(xy[:, 0] - 75.0) + np.abs(xy[:, 1] - 50.0) < 14.0
    z[bench], z[roof] = 50.0, 58.0
    xyz = np.column_stack([xy, z])
    tri = Delaunay(xy)
    assert not raised_segments(xyz, tri, 0.5, 10.0).any()  # the roof is not wholly raised
    drop = raised_segments(xyz, tri, 0.5, 10.0, up_share=0.7, min_lift=2.0)
    assert np.array_equal(drop, roof)
    assert not raised_segments(xyz, tri, 0.5, 10.0, up_share=0.5, min_lift=0.0)[bench].any()
    # It stands ~8 m above the plane through the feet of its steps.
    assert not raised_segments(xyz, tri, 0.5, 10.0, up_share=0.7, min_lift=10.0).any()


def test_supported_points_take_a_cut_crest_but_not_a_bush_or_a_pit():
    rng = np.random.default_rng(13)
    xy = rng.uniform(0, 60, (6000, 2))
    # A sharp ridge along y (45° flanks, crest at 8 m); a labelling that took
    # its flanks up to 6 m and a scatter of the points above.
    z = np.clip(8.0 - np.abs(xy[:, 0] - 20.0), 0.0, None)
    bush = np.hypot(xy[:, 0] - 45.0, xy[:, 1] - 30.0) < 3.0
    z = z + 1.5 * bush
    pit = np.zeros(xy.shape[0], dtype=bool)
    pit[:5] = True
    xy[:5] = [[45.0, 10.0], [50.0, 15.0], [40.0, 50.0], [55.0, 45.0], [48.0, 5.0]]
    z[:5] = -3.0
    xyz = np.column_stack([xy, z])
    crest = ~bush & ~pit & (z >= 6.0)
    ground = ((z < 6.0) & ~bush & ~pit) | (crest & (rng.random(z.size) < 0.3))
    out = supported_points(xyz, ground, radius=1.5, eligible=z >= 0.0, rounds=4)
    assert out[crest].mean() > 0.65  # from 0.3 (measured 0.73; the very top has no ground above it)
    assert not out[bush].any()
    assert not out[pit].any()
    assert np.array_equal(supported_points(xyz, ground, radius=1.5, k=0), ground)


def test_growth_goes_down_further_than_up():
    xy = _grid_nodes(60, 2.0, 14)
    # Flat ground; a 0.4 m terrace down to the east, a 0.4 m platform up to the west.
    z = np.where(xy[:, 0] > 40.0, -0.4, 0.0) + np.where(xy[:, 0] < 20.0, 0.4, 0.0)
    xyz = np.column_stack([xy, z])
    seed = (xy[:, 0] > 25.0) & (xy[:, 0] < 35.0)
    same = grow_ground(xyz, seed, tol=0.2, bend_deg=0.0, max_rise=3.0)
    down = grow_ground(xyz, seed, tol=0.2, bend_deg=0.0, max_rise=3.0, tol_below=0.5)
    assert not same[xy[:, 0] > 41.0].any() and not same[xy[:, 0] < 19.0].any()
    assert down[xy[:, 0] > 41.0].all() and not down[xy[:, 0] < 19.0].any()


def test_growth_keeps_off_barred_nodes():
    xy = _grid_nodes(60, 2.0, 16)
    xyz = np.column_stack([xy, np.zeros(xy.shape[0])])  # flat: growth would take everything
    seed = xy[:, 0] < 10.0
    barred = (np.abs(xy[:, 0] - 40.0) < 6.0) & (np.abs(xy[:, 1] - 30.0) < 6.0)
    ground = grow_ground(xyz, seed, tol=0.2, bend_deg=5.0, max_rise=3.0, barred=barred)
    assert np.array_equal(ground, ~barred)


def test_compiled_growth_rounds_match_the_numpy_rounds():
    # Without agree and reach growth runs compiled, trying again only the edges whose
    # slopes changed; any agree > 0 runs the numpy rounds, and one tiny lets a node join
    # on a single prediction as agree = 0 does: the nodes must be the same, round by round.
    rng = np.random.default_rng(21)
    n = 4000
    xy = rng.uniform(0, 90, (n, 2))
    objects = rng.random(n) < 0.1
    z = 1.5 * np.sin(xy[:, 0] / 9.0) + 0.05 * xy[:, 1] + rng.normal(0, 0.04, n) + 2.0 * objects
    xyz = np.column_stack([xy, z])
    seed = (rng.random(n) < 0.03) & ~objects
    barred = rng.random(n) < 0.02
    kw = dict(tol=0.12, bend_deg=5.0, max_rise=3.0, tol_below=0.24, bend_below_deg=15.0)
    sizes = []
    for rounds in (1, 3, 200):
        a = grow_ground(xyz, seed, barred=barred, max_rounds=rounds, **kw)
        b = grow_ground(xyz, seed, barred=barred, max_rounds=rounds, agree=1e-12, **kw)
        assert np.array_equal(a, b)
        sizes.append(int(a.sum()))
    assert seed.sum() < sizes[0] < sizes[1] < sizes[2] < n - objects.sum()


def test_compiled_medians_and_hull_band_match_numpy():
    from terrasift.workers.ground.raised import _median_per_vertex
    from terrasift.workers.ground.tin import _within_of_hull

    rng = np.random.default_rng(23)
    for t in range(40):
        m, n = int(rng.integers(1, 400)), int(rng.integers(1, 60))
        v = rng.integers(0, n, m)
        # Ties, signed zeros and NaN: the lower middle of np.lexsort's order, bit for bit.
        pool = np.array([0.0, -0.0, 1.0, -1.0, 2.5, np.nan, np.inf])
        value = rng.choice(pool, m) if t % 2 else rng.normal(size=m)
        order = np.lexsort((value, v))
        count = np.bincount(v, minlength=n)
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        want = np.zeros(n)
        want[count > 0] = value[order][(start + (count - 1) // 2)[count > 0]]
        assert np.array_equal(_median_per_vertex(v, value, n).view(np.uint64), want.view(np.uint64))
    xy = rng.uniform(0, 100, (3000, 2))
    hull = Delaunay(xy).convex_hull
    a, b = xy[hull[:, 0]], xy[hull[:, 1]]
    d = b - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    off = np.abs((xy[:, None, 0] - a[:, 0]) * d[:, 1] - (xy[:, None, 1] - a[:, 1]) * d[:, 0])
    near = _within_of_hull(xy, hull, 4.0)
    assert np.array_equal(near, (off / length).min(axis=1) <= 4.0)
    assert 0 < near.sum() < 0.3 * xy.shape[0]


def test_walk_hash_reads_the_bits_of_a_float():
    # A walk cycling on round-off picks its exit edge by a hash of the query's bits.
    import numba

    from terrasift.workers.ground._kernels import _bits

    @numba.njit
    def bits(x):
        out = np.empty(x.size, dtype=np.uint64)
        for i in range(x.size):
            out[i] = _bits(x[i])
        return out

    x = np.array([0.0, -0.0, 1.5, -3.25e8, np.nan, np.inf, -np.inf, 5e-324, 1e300, 512345.67])
    assert np.array_equal(bits(x), x.view(np.uint64))


def test_cell_order_is_the_stable_sort_of_cell_keys():
    rng = np.random.default_rng(9)
    for span in (50.0, 900.0, 3000.0):  # one and two radix passes
        xy = rng.uniform(-span, span, (20000, 2)).round(1)
        key = np.floor(xy[:, 1] / 4.0).astype(np.int64) * 10**6 + np.floor(xy[:, 0] / 4.0).astype(
            np.int64
        )
        assert np.array_equal(cell_order(xy[:, 0], xy[:, 1], 4.0), np.argsort(key, kind="stable"))


def test_nanmedian_first_axis_matches_numpy():
    rng = np.random.default_rng(10)
    a = rng.normal(0, 5, (9, 4000))
    a[rng.random(a.shape) < 0.4] = np.nan
    a[:, :50] = np.nan  # all-NaN columns
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        ref = np.nanmedian(a, axis=0)
    assert np.array_equal(nist._nanmedian_first_axis(a), ref, equal_nan=True)


def test_vertex_deletion_carries_transforms_and_equals_a_fresh_tin():
    rng = np.random.default_rng(11)
    pts = np.column_stack([rng.uniform(0, 100, (4000, 2)), rng.normal(0, 1, 4000)])
    tin = Tin(pts)
    drop = np.zeros(4000, dtype=bool)
    drop[rng.choice(4000, 60, replace=False)] = True
    cut = tin.without(drop)
    fresh = Tin(pts[~drop], origin=tin.origin)
    assert _triangle_set(cut.tri.simplices) == _triangle_set(fresh.tri.simplices)
    assert _neighbour_sets(cut.tri) == _neighbour_sets(fresh.tri)
    assert np.array_equal(cut._transform(), _transforms(cut.xy, cut.tri.simplices), equal_nan=True)


def test_growth_drops_peaks_it_stepped_onto_but_keeps_a_crest():
    xy = _grid_nodes(80, 2.0, 17)
    # A 30° slope up to x = 40, flat beyond; on the flat, bushes as tall as the
    # slope continued: growth from the slope predicts them within tolerance.
    z = np.tan(np.radians(30)) * np.minimum(xy[:, 0], 40.0)
    foot = (xy[:, 0] > 41.0) & (xy[:, 0] < 43.0)
    bush = foot & (np.arange(xy.shape[0]) % 3 == 0)
    z[bush] = np.tan(np.radians(30)) * xy[bush, 0]
    xyz = np.column_stack([xy, z])
    seed = xy[:, 0] < 20.0
    kw = {"tol": 0.3, "bend_deg": 5.0, "max_rise": 3.0}
    plain = grow_ground(xyz, seed, **kw)
    assert plain[bush].any()  # the rule has something to do
    ground = grow_ground(xyz, seed, peak=0.3, **kw)
    assert not ground[bush].any()
    assert ground[~bush].all()


def test_growth_reach_makes_a_node_depend_only_on_nodes_within_it():
    # An embankment 3 m high with vertical walls along x, reached only by a
    # ramp at its east end: growth walks onto it there and along its top. Cut
    # the nodes off west of the ramp (a block's edge) and without a reach the
    # top far from the cut changes; with one it does not.
    xy = _grid_nodes(140, 2.0, 23)
    x = xy[:, 0]
    bank = np.abs(xy[:, 1] - 70.0) < 10.0
    z = np.where(bank, 3.0 * np.clip((130.0 - x) / 30.0, 0.0, 1.0), 0.0)
    xyz = np.column_stack([xy, z])
    seed = z < 0.5
    kw = {"tol": 0.3, "bend_deg": 7.0, "max_rise": 2.5}
    kept = x < 95.0  # the ramp cut off
    far = kept & bank & (x < 95.0 - 40.0 - 5.0)
    whole = grow_ground(xyz, seed, **kw)
    cut = grow_ground(xyz[kept], seed[kept], **kw)
    assert whole[far].all()  # the whole top grown from the ramp...
    assert not cut[far[kept]].any()  # ...and none of it without the ramp
    whole = grow_ground(xyz, seed, reach=40.0, **kw)
    cut = grow_ground(xyz[kept], seed[kept], reach=40.0, **kw)
    near_ramp = bank & (x > 90.0) & (x < 100.0)
    assert whole[near_ramp].all()  # within reach of the ramp's foot: still grown
    assert not whole[far].any()
    assert np.array_equal(whole[kept][x[kept] < 50.0], cut[x[kept] < 50.0])


def test_growth_peak_rule_keeps_a_cut_ridge():
    xy = _grid_nodes(120, 2.0, 11)
    ridge = np.clip(10.0 - np.tan(np.radians(30)) * np.abs(xy[:, 0] - 40.0), 0.0, None)
    hill = np.clip(
        6.0 - 0.01 * ((xy[:, 0] - 90.0) ** 2 + (xy[:, 1] - 60.0) ** 2), 0.0, None
    )  # rounded
    xyz = np.column_stack([xy, ridge + hill])
    seed = xyz[:, 2] < 3.0
    ground = grow_ground(xyz, seed, tol=0.3, bend_deg=7.0, max_rise=3.0, peak=0.3, peak_nodes=6)
    # A knife-edge crest loses the odd node or short group where the jitter
    # leaves it above all its neighbours (5 of 3600 here; support.py takes
    # their points back); the rounded hilltop, wider than 6 nodes, stays.
    assert ground[xyz[:, 2] < 9.5].all()
    assert np.count_nonzero(~ground) <= 6


def test_growth_drops_small_level_groups_standing_above_the_ground():
    xy = _grid_nodes(80, 2.0, 17)
    # The slope of the test above; on the flat, a shed roof level with the
    # slope's top plus 1.2 m (three nodes here), grown onto from the slope.
    top = np.tan(np.radians(30)) * 40.0
    z = np.tan(np.radians(30)) * np.minimum(xy[:, 0], 40.0)
    shed = (xy[:, 0] > 40.5) & (xy[:, 0] < 44.5) & (np.abs(xy[:, 1] - 40.0) < 2.0)
    z[shed] = top + 1.2
    xyz = np.column_stack([xy, z])
    seed = xy[:, 0] < 20.0
    kw = {"tol": 0.3, "bend_deg": 5.0, "max_rise": 3.0, "tol_below": 0.6}
    assert grow_ground(xyz, seed, **kw)[shed].sum() >= 2  # grown onto, more than one node
    assert grow_ground(xyz, seed, peak=0.3, **kw)[shed].any()  # single peaks only: it stays
    ground = grow_ground(xyz, seed, peak=0.3, peak_nodes=6, **kw)
    assert not ground[shed].any()
    assert ground[~shed].all()


def test_hilbert_key_walks_a_grid_one_step_at_a_time():
    rng = np.random.default_rng(12)
    g = np.arange(64.0)
    xy = np.column_stack([np.tile(g, 64), np.repeat(g, 64)])[rng.permutation(4096)]
    key = hilbert_key(xy)
    assert np.array_equal(np.sort(key), np.arange(4096))
    path = xy[np.argsort(key)]
    assert (np.abs(np.diff(path, axis=0)).sum(axis=1) == 1).all()


def test_walks_do_not_depend_on_the_batch_they_run_in():
    rng = np.random.default_rng(13)
    tin = Tin(np.column_stack([rng.uniform(0, 50, (3000, 2)), rng.normal(0, 1, 3000)]))
    q = rng.uniform(-10, 60, (20000, 2)) - tin.origin
    t, bary = tin.locate(q)
    h, sl = tin.height_and_slope(q)
    parts = [q[:777], q[777:13000], q[13000:]]
    t2 = np.concatenate([tin.locate(p)[0] for p in parts])
    bary2 = np.concatenate([tin.locate(p)[1] for p in parts])
    h2 = np.concatenate([tin.height_and_slope(p)[0] for p in parts])
    sl2 = np.concatenate([tin.height_and_slope(p)[1] for p in parts])
    assert np.array_equal(t, t2) and np.array_equal(bary, bary2)
    assert np.array_equal(h, h2) and np.array_equal(sl, sl2)
    assert (t < 0).any() and (t >= 0).any()  # both inside and outside queries were walked


def test_scattered_points_are_inserted_in_hilbert_order_and_coherent_ones_as_given():
    rng = np.random.default_rng(14)
    xy = rng.uniform(0, 100, (5000, 2))
    rows = xy[np.lexsort((xy[:, 0], np.floor(xy[:, 1] / 5.0)))]  # cell order, as ground.nist passes
    assert tin_module._insertion_order(rows) is None
    order = tin_module._insertion_order(xy)
    assert np.array_equal(order, np.argsort(hilbert_key(xy), kind="stable"))
    assert _triangle_set(delaunay(xy).simplices) == _triangle_set(Delaunay(xy).simplices)


def test_band_codes_agree_with_heights_and_slopes():
    rng = np.random.default_rng(21)
    xy = rng.uniform(0, 40, (2000, 2))
    tin = Tin(np.column_stack([xy, 0.3 * xy[:, 0] + rng.normal(0, 0.5, 2000)]))
    pts = np.column_stack([rng.uniform(-5, 45, (30000, 2)), rng.uniform(-3, 15, 30000)])
    h, slope = tin.height_and_slope(pts[:, :2] - tin.origin)
    r = pts[:, 2] - h
    for up, down, gain, cap in [
        (0.5, 1.0, 0.0, np.inf),
        (0.3, 0.2, 0.8, 0.6),
        (0.4, np.inf, 2.0, 1.0),
    ]:
        allow = gain * np.minimum(slope, cap)
        code = tin.band(pts, up, down, gain, cap)
        above = r > up + allow
        inside = ~above & (r >= -(down + allow))
        assert np.array_equal(code == ABOVE, above)
        assert np.array_equal(code == IN_BAND, inside)
        assert np.array_equal(code == BELOW, ~above & ~inside)
        assert above.any() and inside.any()


def test_point_file_screening_has_its_own_tolerance():
    # Pass 2 screens the mowed points against the lowest points of the cells
    # around them, with ``screen_points_tol``, not the TIN's ``screen_tol``.
    g = np.arange(0.0, 20.0, 0.5)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    xyz = np.column_stack([x, y, 0.05 * x])
    xyz = np.vstack([xyz, [10.25, 10.25, 0.05 * 10.25 + 0.9]])
    spacing = nist.point_spacing(xyz[:, :2])
    top = xyz.shape[0] - 1

    def kept(**over: float) -> NDArray[np.int64]:
        return nist._screen_points(xyz, nist.NistParams(**over), spacing)

    assert top in kept() and top in kept(screen_tol=0.5)
    assert top not in kept(screen_points_tol=0.75) and top not in kept(
        screen_tol=2.0, screen_points_tol=0.75
    )
    assert kept(screen_points_tol=0.75).size == xyz.shape[0] - 1


def test_default_raised_step_takes_a_low_roof_whose_border_climbs_in_small_steps():
    # A 1.2 m roof whose border the TIN climbs in 0.4 m steps (vertices on the
    # eaves and a parapet between ground and roof): no edge rises 0.5 m, each 0.4 m.
    xy = _grid_nodes(60, 1.0, 7)
    d = np.maximum(np.abs(xy[:, 0] - 30.0), np.abs(xy[:, 1] - 30.0))
    z = np.select([d < 6.0, d < 8.0, d < 10.0], [1.2, 0.8, 0.4], 0.0)
    xyz = np.column_stack([xy, z])
    tri = Delaunay(xy)
    p = nist.NistParams()
    drop = raised_segments(
        xyz, tri, p.raised_step, p.raised_slope, up_share=p.raised_share, min_lift=p.raised_lift
    )
    assert np.array_equal(drop, d < 10.0)
    assert not raised_segments(xyz, tri, 0.5, p.raised_slope).any()


def test_screening_votes_follow_bin_planes_only_up_to_the_slope_cap():
    # A deck vertex 5 m up, ringed by bins astride its walls: their planes rise
    # 4 m/m towards it, so votes extrapolated along them (+8 m over 4 m) vouch
    # for the deck. Capped at 1.5 (56°, steeper than terrain) they do not.
    ang = np.radians(np.arange(0, 360, 60) + 7.0)
    ring = 4.0 * np.column_stack([np.cos(ang), np.sin(ang)])
    xy = np.vstack([[0.0, 0.0], ring])
    z = np.r_[5.0, np.zeros(6)]
    slopes = -4.0 * np.vstack([[0.0, 0.0], ring]) / 4.0  # gradients pointing up towards the deck
    kept_uncapped, _ = screen(
        np.column_stack([xy, z]), 1.0, 0.0, slopes=nist._vote_slopes(slopes, 0.0)
    )
    kept_capped, _ = screen(
        np.column_stack([xy, z]), 1.0, 0.0, slopes=nist._vote_slopes(slopes, 1.5)
    )
    assert 0 in kept_uncapped and 0 not in kept_capped
    assert set(kept_capped) == set(range(1, 7))
    # Gentle planes pass unchanged; steep ones keep their direction; NaN is level.
    v = nist._vote_slopes(np.array([[0.3, -0.4], [3.0, 4.0], [np.nan, np.nan]]), 1.5)
    assert np.allclose(v, [[0.3, -0.4], [0.9, 1.2], [0.0, 0.0]])


def test_slivers_along_the_data_edge_cast_no_screening_vote():
    # A plateau 40 m up reaching the data's lower edge (y = 0) at one vertex a
    # little inside it; the terrain along that edge is 40 m away either side.
    # The TIN joins that vertex to the terrain by slivers along the edge: they
    # voted it down, then the next plateau vertex became the outline and went
    # too, until the whole plateau was screened away. Six-metre bins, slivers
    # longer than 4 bins within a bin of the outline: no vote.
    low = [(x, y, 0.0) for x in (-60.0, -40.0, 40.0, 60.0) for y in (0.0, 12.0, 24.0, 36.0)]
    top = [(0.0, 0.4, 40.0)] + [(x, y, 40.0) for x in (-3.0, 3.0) for y in range(6, 37, 6)]
    xyz = np.array(low + top, dtype=np.float64)
    flat = np.zeros((xyz.shape[0], 2))
    plateau = set(range(len(low), xyz.shape[0]))
    old, _ = screen(xyz, 3.0, 4.0, slopes=flat)
    new, _ = screen(xyz, 3.0, 4.0, slopes=flat, rim_len=24.0, rim_band=6.0)
    assert not plateau & set(old)
    assert plateau <= set(new) and len(new) == xyz.shape[0]
    # A spike inside the outline is still voted down.
    spike = np.vstack([xyz, [50.0, 20.0, 30.0]])
    kept, _ = screen(
        spike, 3.0, 4.0, slopes=np.zeros((spike.shape[0], 2)), rim_len=24.0, rim_band=6.0
    )
    assert spike.shape[0] - 1 not in kept


def test_within_of_hull_measures_distance_to_the_outline():
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [5.0, 5.0], [5.0, 0.5]])
    edges = Delaunay(xy).convex_hull
    assert tin_module._within_of_hull(xy, edges, 1.0).tolist() == [True] * 4 + [False, True]
    assert tin_module._within_of_hull(xy, edges, 5.0).all()


def test_growth_bends_faster_going_down_over_a_crest():
    # Nodes 3.5 m apart (sparse data); a sharp ridge with 30° flanks along y,
    # seeded on its west side only: the east side is reached over the crest,
    # where the slope turns from +0.58 to -0.58 within one edge.
    xy = _grid_nodes(120, 3.5, 11)
    ridge = np.clip(10.0 - np.tan(np.radians(30)) * np.abs(xy[:, 0] - 40.0), 0.0, None)
    roof = (np.abs(xy[:, 0] - 95.0) < 10) & (np.abs(xy[:, 1] - 60.0) < 10)
    xyz = np.column_stack([xy, ridge + 6.0 * roof])
    seed = (xyz[:, 2] < 3.0) & ~roof & (xy[:, 0] < 40.0)
    east = (xy[:, 0] > 41.0) & ~roof
    kw = {"tol": 0.3, "tol_below": 0.6, "bend_deg": 5.0, "max_rise": 3.0}
    same = grow_ground(xyz, seed, **kw)
    down = grow_ground(xyz, seed, bend_below_deg=15.0, **kw)
    assert not same[east].all()
    assert down[east].all() and down[xy[:, 0] < 39.0].all()
    assert not down[roof].any()


def test_snapped_cells_divide_the_anchor_and_absorb_small_density_differences():
    from terrasift.workers.bins import ANCHOR, snap_cell

    for c in (1.0, 1.37, 2.2, 3.6, 9.6, 14.0, 23.7, 45.0):
        s = snap_cell(c)
        assert abs(ANCHOR / s - round(ANCHOR / s)) < 1e-9
        assert 0.8 < s / c < 1.2
    # Two blocks whose spacings differ by 5 % bin alike; sizes outside the ladder stay.
    assert snap_cell(10 * 2.40) == snap_cell(10 * 2.52)
    assert snap_cell(0.5) == 0.5 and snap_cell(500.0) == 500.0
    # Off, auto cells follow the spacing as they are.
    xyz = make_scene(120, 0.3, seed=2).xyz
    spacing = nist.point_spacing(xyz[:, :2])
    on = nist._grids(xyz, nist.NistParams(), spacing, None)
    off = nist._grids(xyz, nist.NistParams(snap_cells=False), spacing, None)
    assert on[0].cell == snap_cell(off[0].cell) and on[0].cell != off[0].cell


def test_labels_of_2x2_blocks_agree_with_one_run_on_sparse_data():
    # 0.3 pts/m²: cells of 18, 7 and 2.7 m derived per block from each block's density.
    sc = make_scene(240, 0.3, seed=7)
    xyz = sc.xyz
    params = nist.NistParams()
    whole = nist.classify_ground(xyz, params)
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    mid = (lo + hi) / 2
    halo = params.halo(xyz.shape[0] / float(np.prod(hi - lo)))
    split = np.zeros_like(whole)
    for qx in (False, True):
        for qy in (False, True):
            core = ((xyz[:, 0] >= mid[0]) == qx) & ((xyz[:, 1] >= mid[1]) == qy)
            c_lo = np.where([qx, qy], mid, lo)
            c_hi = np.where([qx, qy], hi, mid)
            sub = np.all((xyz[:, :2] >= c_lo - halo) & (xyz[:, :2] <= c_hi + halo), axis=1)
            idx = np.flatnonzero(sub)
            g = nist.classify_ground(xyz[idx], params)
            split[idx[core[idx]]] = g[core[idx]]
    # Measured: 99.98 % with snapped cells, 99.81 % with cells following each block's density.
    assert (split == whole).mean() >= 0.9995


def _job_anchor(xyz: np.ndarray) -> tuple[float, float]:
    """The anchor a job gives data-anchored bins: the centre of its tile's bounds."""
    c = (xyz[:, :2].min(axis=0) + xyz[:, :2].max(axis=0)) / 2
    return float(c[0]), float(c[1])


def _split_2x2(xyz: np.ndarray, params: nist.NistParams, window: bool = False) -> np.ndarray:
    """Labels of each core of a 2 × 2 split (with the stage's halo), as one array;
    with ``window``, each block is told the box it was cut to."""
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    mid = (lo + hi) / 2
    halo = max(params.halo(xyz.shape[0] / float(np.prod(hi - lo))), 20.0)
    split = np.zeros(xyz.shape[0], dtype=bool)
    for qx in (False, True):
        for qy in (False, True):
            core = ((xyz[:, 0] >= mid[0]) == qx) & ((xyz[:, 1] >= mid[1]) == qy)
            c_lo = np.where([qx, qy], mid, lo)
            c_hi = np.where([qx, qy], hi, mid)
            sub = np.all((xyz[:, :2] >= c_lo - halo) & (xyz[:, :2] <= c_hi + halo), axis=1)
            idx = np.flatnonzero(sub)
            box = (*(c_lo - halo), *(c_hi + halo)) if window else None
            g = nist.classify_ground(xyz[idx], params, window=box)
            split[idx[core[idx]]] = g[core[idx]]
    return split


def test_relative_steps_keep_a_hill_with_steep_slopes_and_drop_a_platform():
    rng = np.random.default_rng(3)
    g = np.arange(1.0, 160.0, 3.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.3, 0.3, (g.size**2, 2))
    # A plateau 30 m across on a hill whose sides fall at 25°, on level ground.
    r = np.hypot(xy[:, 0] - 50.0, xy[:, 1] - 80.0)
    z = np.clip(np.tan(np.radians(25)) * (45.0 - np.maximum(r, 15.0)), 0.0, None)
    # A platform 1 m high, 6 m wide, 60 m long on the level ground beside it.
    platform = (np.abs(xy[:, 0] - 125.0) < 3.0) & (np.abs(xy[:, 1] - 80.0) < 30.0)
    z = z + 1.0 * platform
    xyz = np.column_stack([xy, z])
    tri = Delaunay(xy)
    # Its walls rise out of level ground: a step either way; the hill's slope
    # edges continue the slope below them and are no steps measured relatively.
    for relative in (False, True):
        assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, relative=relative), platform)
    e = tin_edges(tri)
    dz = np.abs(xyz[e[:, 1], 2] - xyz[e[:, 0], 2])
    on_hill = (r[e[:, 0]] < 44.0) & (r[e[:, 1]] < 44.0) & (dz >= 0.3)
    assert on_hill.sum() > 100  # slope edges that would be steps measured against level


def test_wall_share_keeps_a_hilltop_cut_off_by_slope_edges_and_drops_a_platform():
    # A plateau 30 m across on a cone falling at 30°, its slope sampled by rings
    # 3 m apart (as bins of a sparse pass fall): every radial edge is a step
    # against level, so the plateau is the upper side of all its steps.
    g = np.arange(-13.5, 14.0, 3.0)
    pl = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pl = pl[np.hypot(*pl.T) < 14.0]
    tan30 = np.tan(np.radians(30))
    pts = [np.column_stack([pl, np.full(len(pl), tan30 * 25.0)])]
    for r in np.arange(18.0, 41.0, 3.0):
        a = np.linspace(0, 2 * np.pi, int(2 * np.pi * r / 3.0), endpoint=False)
        pts.append(
            np.column_stack([r * np.cos(a), r * np.sin(a), np.full(a.size, tan30 * (40 - r))])
        )
    hill = np.concatenate(pts) + np.array([60.0, 80.0, 0.0])
    # Level ground around it, and a platform 1 m high, 6 m wide, 60 m long.
    gx = np.arange(1.0, 180.0, 3.0)
    ground = np.stack(np.meshgrid(gx, gx), -1).reshape(-1, 2)
    ground = ground[np.hypot(ground[:, 0] - 60.0, ground[:, 1] - 80.0) > 43.0]
    platform = (np.abs(ground[:, 0] - 150.0) < 3.0) & (np.abs(ground[:, 1] - 80.0) < 30.0)
    xyz = np.concatenate([hill, np.column_stack([ground, 1.0 * platform])])
    top = np.zeros(len(xyz), dtype=bool)
    top[: len(pts[0])] = True
    is_platform = np.r_[np.zeros(len(hill), dtype=bool), platform]
    tri = Delaunay(xyz[:, :2])
    level = raised_segments(xyz, tri, 0.3, 10.0)
    assert level[top].all() and level[is_platform].all()  # the hilltop goes with level steps
    walled = raised_segments(xyz, tri, 0.3, 10.0, walls=0.5)
    assert not walled[top].any() and np.array_equal(walled, is_platform)


def test_rise_makes_a_platform_seen_across_a_hole_a_walled_segment():
    # A platform 1 m high, 6 m wide, 60 m long, in a hole of the TIN 7 m wide
    # all round (wagons beside it were dropped): it meets the ground only by
    # edges 7 m and longer, at under 10°, so no edge is a step by its gradient.
    g = np.arange(0.0, 150.0, 3.0)
    ground = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    hole = (np.abs(ground[:, 0] - 75.0) < 3.0 + 7.0) & (np.abs(ground[:, 1] - 75.0) < 30.0 + 7.0)
    ground = ground[~hole]
    px, py = np.meshgrid(np.arange(72.25, 78.0, 1.5), np.arange(45.25, 105.0, 1.5))
    plat = np.column_stack([px.ravel(), py.ravel()])
    xyz = np.concatenate(
        [
            np.column_stack([ground, np.zeros(len(ground))]),
            np.column_stack([plat, np.ones(len(plat))]),
        ]
    )
    is_platform = np.r_[np.zeros(len(ground), dtype=bool), np.ones(len(plat), dtype=bool)]
    tri = Delaunay(xyz[:, :2])
    assert not raised_segments(xyz, tri, 0.3, 10.0, walls=0.5).any()
    drop = raised_segments(xyz, tri, 0.3, 10.0, walls=0.5, rise=0.3)
    assert np.array_equal(drop, is_platform)
    # The same patch 0.6–1.8 m high, rolling gently (no step inside it, RMS ~0.4 m
    # about its plane): terrain seen across a hole, not a flat top; long edges
    # alone do not cut it off (they would without the flatness rule).
    rolling = xyz.copy()
    rolling[is_platform, 2] += 0.2 + 0.6 * np.sin(rolling[is_platform, 1] / 10.0)
    assert not raised_segments(rolling, tri, 0.3, 10.0, walls=0.5, rise=0.3).any()


def test_rim_slivers_do_not_join_a_platform_at_the_data_edge_to_far_ground():
    # Ground rising 2.5 % to the east, a platform 1 m high, 6 m wide, 40 m long
    # reaching the south edge of the data. Its vertex at the edge lies just inside
    # the hull, which runs along y = 0 from (60, 0) to (140, 0): the sliver between
    # them joins the platform, by an edge 37 m long and 0.08 m high, to a hull
    # vertex (so to ground kept as on the hull).
    rng = np.random.default_rng(5)
    g = np.arange(0.0, 200.0, 1.5)
    xy = np.stack(np.meshgrid(g, g[1:]), -1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.2, 0.2, xy.shape)
    xy = np.concatenate([xy, [[0.0, 0.0], [60.0, 0.0], [140.0, 0.0], [199.0, 0.0], [103.0, 0.01]]])
    platform = (np.abs(xy[:, 0] - 103.0) < 3.0) & (xy[:, 1] < 40.0)
    xyz = np.column_stack([xy, 0.025 * xy[:, 0] + 1.0 * platform])
    tri = Delaunay(xy)
    kw = {"walls": 0.5, "rise": 0.3}
    assert not raised_segments(xyz, tri, 0.3, 10.0, **kw).any()
    assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, rim=4.0, **kw), platform)
    # It reaches the edge along its 6 m end only: not kept as reaching the data's edge.
    assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, rim=4.0, edge=20.0, **kw), platform)


def test_a_plateau_crossing_the_data_is_kept_whether_or_not_it_holds_a_hull_vertex():
    # A plateau 50 m wide and 20 m high crossing the data from south to north,
    # walled on both long sides, on level ground. Its vertices at the data's
    # edge lie 0.2 m inside the line through the others, so none is a hull
    # vertex (as after a 1 cm rounding on tile 54 of the steep family).
    rng = np.random.default_rng(3)
    g = np.arange(0.0, 200.0, 1.5)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.05, 0.05, xy.shape) * (xy > 0) * (xy < g[-1])
    plateau = np.abs(xy[:, 0] - 100.0) < 25.0
    xy[plateau, 1] = np.clip(xy[plateau, 1], 0.2, g[-1] - 0.2)
    xyz = np.column_stack([xy, 20.0 * plateau])
    tri = Delaunay(xy)
    assert not plateau[np.unique(tri.convex_hull)].any()
    kw = {"walls": 0.5, "rise": 0.3, "rim": 4.0}
    assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, **kw), plateau)  # hull rule
    assert not raised_segments(xyz, tri, 0.3, 10.0, edge=20.0, **kw).any()
    # The same plateau shortened to end 20 m inside the data is a roof.
    inside = plateau & (xy[:, 1] > 20.0) & (xy[:, 1] < 180.0)
    xyz[:, 2] = 20.0 * inside
    assert np.array_equal(raised_segments(xyz, tri, 0.3, 10.0, edge=20.0, **kw), inside)


def test_a_roof_crossing_a_block_cut_is_judged_by_its_walls_not_kept_as_at_the_data_edge():
    # Two sheds 30 m wide on level ground, walled on their long sides: one runs
    # out of the north side of the box the points were cut to (a block's halo:
    # the data goes on beyond), one out of the south edge of the data.
    rng = np.random.default_rng(4)
    g = np.arange(0.0, 200.0, 1.5)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy + rng.uniform(-0.2, 0.2, xy.shape)
    north = (np.abs(xy[:, 0] - 60.0) < 15.0) & (xy[:, 1] > 120.0)
    south = (np.abs(xy[:, 0] - 140.0) < 15.0) & (xy[:, 1] < 80.0)
    xyz = np.column_stack([xy, 4.0 * (north | south)])
    tri = Delaunay(xy)
    kw = {"walls": 0.5, "rise": 0.3, "rim": 4.0, "edge": 20.0}
    # Without the box both reach the edge of the data along 30 m: both kept.
    assert not raised_segments(xyz, tri, 0.3, 10.0, **kw).any()
    cut = (-100.0, -100.0, 300.0, float(g[-1]) + 0.5)  # only the north side lies at the data
    drop = raised_segments(xyz, tri, 0.3, 10.0, cut=cut, **kw)
    assert np.array_equal(drop, north)


def test_a_shed_crossing_a_block_cut_is_labelled_as_in_one_run():
    # Railway yard 100 (a 100 m shed crosses the cut between blocks), each block
    # given the job's density. Measured: 98.99 % of labels alike when each block
    # takes the edge of its halo for the edge of the data, 99.99 % when told its box.
    from terrasift.tiling.blocks import occupancy_cell, occupied_cells, occupied_density

    xyz = rural.FAMILIES["railway_yard"](100).xyz
    cell = occupancy_cell(xyz.shape[0] / float(np.prod(np.ptp(xyz[:, :2], axis=0))))
    density = occupied_density(xyz.shape[0], [occupied_cells(xyz[:, 0], xyz[:, 1], cell)], cell)
    params = nist.NistParams(density=density, anchor=_job_anchor(xyz))
    whole = nist.classify_ground(xyz, params)
    assert (_split_2x2(xyz, params, window=True) == whole).mean() >= 0.999
    assert (_split_2x2(xyz, params) == whole).mean() < 0.995


def test_masking_off_keeps_a_low_platform_out_of_the_ground():
    # Railway yard seed 97 (2.0 pts/m², a tuning seed): a platform 0.8 m high and 127 m
    # long. Masking marks its walls, so the bins beside it are rejected and its top
    # passes as ground (Type II 19.9 %); without masking 0.5 %. Measured without
    # ``raised_even`` and ``raised_over_walls`` (later), which drop that top with masking
    # on too (0.5 %).
    from terrasift.synthetic import rural

    sc = rural.FAMILIES["railway_yard"](97)
    truth = sc.truth == 2
    masked = ground_score(
        truth,
        nist.classify_ground(
            sc.xyz, nist.NistParams(mask=True, raised_even=False, raised_over_walls=False)
        ),
    )
    plain = ground_score(truth, nist.classify_ground(sc.xyz, nist.NistParams()))
    assert masked.type2 > 0.10
    assert plain.type2 < 0.02 and plain.type1 < 0.01


def test_a_gentle_edge_across_a_platform_wall_does_not_join_it_to_the_terrain():
    # Railway yard seed 97 moved by (0, 0.5) m on absolute bins: one final-TIN edge runs
    # 3 m from the ground up to the 0.8 m platform's top, at 8°, gentler than a step, and
    # joins the platform to the terrain (Type II 20 %). The returns over its middle lie at
    # the foot and at the top, none on its ramp: it crosses the wall, so it is a step.
    from terrasift.synthetic import rural

    sc = rural.FAMILIES["railway_yard"](97)
    truth = sc.truth == 2
    xyz = sc.xyz + np.array([0.0, 0.5, 0.0])
    p = nist.NistParams(bin_anchor="absolute")
    joined = ground_score(
        truth, nist.classify_ground(xyz, p.model_copy(update={"raised_over_walls": False}))
    )
    crossed = ground_score(truth, nist.classify_ground(xyz, p))
    assert joined.type2 > 0.10  # measured 20.03 %
    assert crossed.type2 < 0.02 and crossed.type1 < 0.01  # measured 0.63 / 0.00 %


def test_growth_needs_its_ground_neighbours_to_agree_before_climbing_a_platform():
    # Railway yard seed 103 (0.96 pts/m², a tuning seed): slopes fitted at the foot of
    # platforms from two close ground nodes predicted the tops; growth then spread
    # over them (Type II 14 %). With grow_agree=0.5 half of a node's ground
    # neighbours must predict it. Measured with masking on, as when the rule was made,
    # and without walled plateaus (which drop those tops after growth).
    from terrasift.synthetic import rural

    sc = rural.FAMILIES["railway_yard"](103)
    truth = sc.truth == 2
    anyone = ground_score(
        truth, nist.classify_ground(sc.xyz, nist.NistParams(mask=True, plateau_step=0.0))
    )
    half = ground_score(
        truth,
        nist.classify_ground(sc.xyz, nist.NistParams(mask=True, grow_agree=0.5, plateau_step=0.0)),
    )
    assert anyone.type2 > 0.10
    assert half.type2 < 0.03 and half.type1 < 0.01


def test_auto_vote_runs_one_grid_on_dense_data_and_four_on_sparse():
    dense = make_scene(size=60.0, density=8.0, seed=3).xyz
    sparse = make_scene(size=120.0, density=0.5, seed=3).xyz
    # Without the roughness test, which here takes back every point the phases differ on.
    p = nist.NistParams(rough_k=0)
    assert np.array_equal(
        nist.classify_ground(dense, p),
        nist.classify_ground(dense, p.model_copy(update={"vote_phases": 1})),
    )
    auto = nist.classify_ground(sparse, p)
    assert np.array_equal(
        auto, nist.classify_ground(sparse, p.model_copy(update={"vote_phases": 2}))
    )
    assert not np.array_equal(
        auto, nist.classify_ground(sparse, p.model_copy(update={"vote_phases": 1}))
    )


def test_walled_plateaus_drop_a_platform_growth_climbed_but_keep_a_grown_crest():
    from terrasift.workers.ground.plateaus import walled_plateaus

    rng = np.random.default_rng(4)
    g = np.arange(0.0, 60.0, 1.5)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.2, 0.2, (g.size**2, 2))
    # A platform 1 m high (x 10–16, y 10–50) with vertical walls, and a dike 2 m high
    # (x 35–50) whose sides fall at 1:1.5 onto level ground.
    platform = (np.abs(xy[:, 0] - 13.0) < 3.0) & (np.abs(xy[:, 1] - 30.0) < 20.0)
    d = np.abs(xy[:, 0] - 42.5)
    z = 1.0 * platform + np.clip((7.5 - d) / 1.5, 0.0, 2.0) + rng.normal(0, 0.02, len(xy))
    # The passes found the level ground (seeds); growth added the platform top and the
    # whole dike, its sides included.
    seed = ~platform & (d >= 7.5)
    ground = np.ones(len(xy), dtype=bool)
    adjacency = Delaunay(xy).vertex_neighbor_vertices
    drop = walled_plateaus(z, ground, seed, adjacency, margin=0.18, step=0.5, share=1.0)
    assert np.array_equal(drop, platform)
    # Without the walls (a ramp onto its top from the seeds) the platform stays.
    ramp = platform | ((np.abs(xy[:, 0] - 13.0) < 6.0) & (np.abs(xy[:, 1] - 30.0) < 20.0))
    z2 = np.where(ramp & ~platform, np.clip(1.0 - (np.abs(xy[:, 0] - 13.0) - 3.0) / 3.0, 0, 1), z)
    seed2 = ~ramp & (d >= 7.5)
    drop2 = walled_plateaus(z2, ground, seed2, adjacency, margin=0.18, step=0.5, share=1.0)
    assert not drop2.any()


def test_walled_plateaus_take_railway_platforms_off_the_ground():
    # Railway yard seed 103 (0.96 pts/m², a tuning seed): growth climbs a platform
    # 0.8 m high from slopes fitted at its foot (Type II 7.8 % with the vote); its top
    # drops straight onto the passes' ground all round and goes (0.0 % measured).
    from terrasift.synthetic import rural

    sc = rural.FAMILIES["railway_yard"](103)
    truth = sc.truth == 2
    off = ground_score(truth, nist.classify_ground(sc.xyz, nist.NistParams(plateau_step=0.0)))
    on = ground_score(truth, nist.classify_ground(sc.xyz, nist.NistParams()))
    assert off.type2 > 0.05
    assert on.type2 < 0.01 and on.type1 <= off.type1 + 0.001


def test_walled_islands_drop_a_pitched_roof_cut_into_rows_but_keep_a_terrace():
    from terrasift.workers.ground.plateaus import walled_islands

    rng = np.random.default_rng(5)
    g = np.arange(0.0, 110.0, 1.5)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.2, 0.2, (g.size**2, 2))
    x, y = xy[:, 0], xy[:, 1]
    # A gabled roof 20 m wide (x 10–30), 40 m long, eaves 7 m up, ridge 11 m (22°):
    # every row of TIN edges across it climbs 0.6 m at 22°, a step, so the roof is
    # cut into rows, each the lower side of the row above.
    roof = (np.abs(x - 20.0) < 10.0) & (np.abs(y - 45.0) < 20.0)
    z = np.where(roof, 11.0 - 0.4 * np.abs(x - 20.0), 0.0)
    # A terrace on a hillside (x 50–90): a wall 3 m up at x 60, a tread, the slope above.
    z = z + np.where(x > 50.0, np.where(x > 60.0, 3.0 + 0.3 * np.clip(x - 70.0, 0, None), 0.0), 0.0)
    # A steep hill (a cone at 35°, 8.4 m high, 24 m across) whose slope edges cut it
    # into rings.
    r = np.hypot(x - 20.0, y - 88.0)
    hill = r < 12.0
    z = z + np.where(hill, 0.7 * (12.0 - r), 0.0)
    z = z + rng.normal(0, 0.02, len(xy))
    xyz = np.column_stack([xy, z])
    tri = Delaunay(xy)
    gone = raised_segments(xyz, tri, 0.3, 10.0, up_share=0.7, min_lift=1.5, walls=0.5)
    assert not gone[roof].all()  # no single row is raised on its own
    drop = walled_islands(xyz, tri, gone, 0.3, 10.0, walls=0.5, edge=20.0)
    assert (gone | drop)[roof].all()
    assert not drop[hill].any()
    # The hillside stepping up from the terrace wall to the data's edge stays.
    assert not (gone | drop)[x > 40.0].any()


def test_centre_weights_of_the_four_phases_interpolate_between_them():
    # Two phases per axis, half a bin apart: tents that sum to 1 everywhere (the
    # weights of bilinear interpolation), 1 for the phase whose bin is centred on a point.
    g = Grid(0.0, 0.0, 3.0, 40, 40)
    phases = nist._phased(g, 2)
    p = nist.NistParams(vote_weight="centre")
    pts = np.column_stack([np.random.default_rng(1).uniform(0, 100, (500, 2)), np.zeros(500)])
    pts[0, :2] = (16.5, 16.5)  # the centre of a bin of the unshifted grid
    w = np.array([nist._vote_weights(pts, ph, p, 4) for ph in phases])
    assert np.allclose(w.sum(axis=0), 1.0, atol=1e-6)
    assert w[0, 0] == pytest.approx(1.0) and np.allclose(w[1:, 0], 0.0, atol=1e-6)
    assert nist._vote_weights(pts, g, nist.NistParams(), 4) == 1.0


def test_a_larger_vote_share_keeps_fewer_points_as_ground():
    sparse = make_scene(size=120.0, density=0.5, seed=3).xyz
    # Without the roughness test, which here takes back every point the shares differ on.
    half = nist.classify_ground(sparse, nist.NistParams(rough_k=0))
    strict = nist.classify_ground(sparse, nist.NistParams(vote_share=0.75, rough_k=0))
    assert not (strict & ~half).any() and (half & ~strict).any()
    centre = nist.classify_ground(sparse, nist.NistParams(vote_weight="centre", rough_k=0))
    assert not np.array_equal(centre, half)


def test_roughness_takes_shrub_returns_off_a_slope_but_not_a_dike_crest():
    # 0.5 pts/m² on a 30 % slope with 3 cm noise, a dike 2 m high (sides 1:1.5)
    # across it, and eight shrubs whose returns stand 0.3-0.8 m above the ground.
    from terrasift.workers.ground.roughness import rough_points

    rng = np.random.default_rng(4)
    n = 5000
    xy = rng.uniform(0, 100, (n, 2))
    d = np.abs(xy[:, 1] - 50.0)
    dike = 2.0 * np.clip((2.0 + 3.0 - d) / 3.0, 0.0, 1.0)
    z = 0.3 * xy[:, 0] + dike + rng.normal(0, 0.03, n)
    centres = rng.uniform(10, 90, (8, 2))
    near = cKDTree(centres).query(xy)[0] < 2.5
    shrub = near & (rng.random(n) < 0.7) & (dike == 0)
    z[shrub] += rng.uniform(0.3, 0.8, np.count_nonzero(shrub))
    xyz = np.column_stack([xy, z])
    high = rough_points(xyz, np.ones(n, dtype=bool), k=48, factor=5.0, clip=2.0, floor=0.05)
    assert high[shrub].mean() > 0.8, high[shrub].mean()
    assert high[~shrub].mean() < 0.01, high[~shrub].mean()
    crest = (d < 2.0) & ~shrub
    assert high[crest].mean() < 0.05, high[crest].mean()


def test_roughness_labels_a_block_as_the_whole_tile_does():
    # Rough ground (15 cm noise) on the west half, smooth (1 cm) on the east, shrub
    # returns 0.2-0.4 m high on both, 0.5 pts/m². A block of the east half with a 20 m
    # halo must label its core as the whole tile does: the threshold may depend on the
    # ground around a point, not on how much rough ground the block happens to hold.
    from terrasift.workers.ground.roughness import rough_points

    rng = np.random.default_rng(7)
    n = 8000
    xy = rng.uniform(0, 160, (n, 2))
    z = 0.05 * xy[:, 0] + rng.normal(0, np.where(xy[:, 0] < 80, 0.15, 0.01))
    shrub = rng.random(n) < 0.03
    z[shrub] += rng.uniform(0.2, 0.4, np.count_nonzero(shrub))
    xyz = np.column_stack([xy, z])
    args = {"k": 48, "factor": 5.0, "clip": 2.0, "floor": 0.05}
    whole = rough_points(xyz, np.ones(n, dtype=bool), **args)
    block = xy[:, 0] >= 100.0 - 20.0
    part = rough_points(xyz[block], np.ones(np.count_nonzero(block), dtype=bool), **args)
    core = xy[block, 0] >= 100.0
    assert np.array_equal(part[core], whole[block][core])
    assert whole[shrub & (xy[:, 0] >= 100)].mean() > 0.8  # the east's shrubs do go


def test_roughness_rule_runs_on_sparse_data_only_and_takes_low_vegetation_back():
    # Rural slope seed 7 (0.2-1 pts/m², not one of the benchmark's seeds): the filter's
    # band takes shrub returns 0.25-1 m high; the roughness test takes most back.
    from terrasift.synthetic import rural

    sc = rural.FAMILIES["rural_slope"](7)
    truth = sc.truth == 2
    off = ground_score(truth, nist.classify_ground(sc.xyz, nist.NistParams(rough_k=0)))
    on = ground_score(truth, nist.classify_ground(sc.xyz, nist.NistParams()))
    assert on.type2 < 0.6 * off.type2, (on.type2, off.type2)
    assert on.type1 < 0.01
    dense = make_scene(size=60.0, density=8.0, seed=3).xyz
    assert np.array_equal(
        nist.classify_ground(dense, nist.NistParams()),
        nist.classify_ground(dense, nist.NistParams(rough_k=0)),
    )


def test_passes_one_and_two_vote_over_grid_phases_when_asked():
    # mow_share: a point survives a pass's mowing when that share of the phases'
    # surfaces keep it, so "any of them" keeps a superset of "all of them".
    xyz = make_scene(150, 0.5, seed=4).xyz
    local = xyz - np.array([*xyz[:, :2].min(axis=0), 0.0])
    spacing = nist.point_spacing(local[:, :2])
    g1 = nist._grids(local, nist.NistParams(), spacing, None)[0]

    def kept(share: float) -> set[int]:
        params = nist.NistParams(mow_share=share)
        phases = [[nist.select_reject(local, params, g)] for g in nist._phased(g1, 2)]
        centre = local[:, :2].mean(axis=0)
        return set(nist._voted_mow(local, local, phases, params, centre, 1.0, 0.5, g1.cell))

    any_, all_ = kept(0.25), kept(1.0)
    assert all_ < any_  # strictly: the phases' surfaces differ somewhere
    assert len(all_) > 0.5 * len(local)


def test_grow_share_adds_what_growth_reached_in_that_share_of_phases_only():
    # A sparse scene votes over 4 final phases. With ``grow_share`` a point that
    # growth added in one phase (of four: share 0.25) is ground; everything the
    # majority labels stays. Without growth there is nothing to add.
    sparse = make_scene(size=120.0, density=1.0, seed=1).xyz
    p = nist.NistParams(rough_k=0)
    base = nist.classify_ground(sparse, p)
    any_phase = nist.classify_ground(sparse, p.model_copy(update={"grow_share": 0.25}))
    assert np.all(any_phase[base])
    assert np.count_nonzero(any_phase & ~base) > 0
    off = p.model_copy(update={"grow": False})
    assert np.array_equal(
        nist.classify_ground(sparse, off),
        nist.classify_ground(sparse, off.model_copy(update={"grow_share": 0.25})),
    )


def test_square_nodes_label_a_translated_tile_alike_where_bins_do_not():
    # ``final_nodes="square"``: every pass meshes the points lowest in the cell-sized
    # square around them, a rule of the data, so a translation by a fraction of a bin
    # (a tile origin falling elsewhere) gives the same labels; the bins' do not (17 of
    # 6 589 points move on this sparse rural slope).
    xyz = rural.FAMILIES["rural_slope"](0).xyz
    xyz = xyz[xyz[:, 0] < xyz[:, 0].min() + 60.0]
    move = np.array([0.7, 1.1, 0.0])
    # The density given, as a job gives it: measured, it follows occupied cells of a grid.
    # Without the close fit (``rough_fit``): its thresholds flip one point of these under
    # the move (rounding of the moved coordinates), the square nodes' rule is judged here.
    p = nist.NistParams(density=0.5, rough_fit=0, bin_anchor="absolute")
    sq = p.model_copy(update={"final_nodes": "square"})
    assert np.array_equal(nist.classify_ground(xyz, sq), nist.classify_ground(xyz + move, sq))
    bins = nist.classify_ground(xyz, p)
    assert np.count_nonzero(bins != nist.classify_ground(xyz + move, p)) > 5


def test_square_lowest_picks_the_dip_of_each_square_and_moves_with_the_data():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 30, (600, 2))
    z = 0.2 * xy[:, 0] + rng.normal(0, 0.02, 600)  # a 20 % slope: the plane, not the level, decides
    z[100] -= 1.0
    xyz = np.column_stack([xy, z])
    idx, grads = square_lowest(xyz, 3.0)
    assert 100 in idx
    near = np.max(np.abs(xy - xy[100]), axis=1) <= 1.5
    assert not np.isin(np.flatnonzero(near & (np.arange(600) != 100)), idx).any()
    assert np.allclose(np.median(grads[:, 0]), 0.2, atol=0.05)
    moved, _ = square_lowest(xyz + np.array([123.4, -56.7, 0.0]), 3.0)
    assert np.array_equal(idx, moved)
    assert square_lowest(xyz, 3.0, z_tol=1e-6)[0].size < idx.size / 10  # lone points only


def test_points_on_bin_edges_fall_in_the_same_bins_whatever_the_anchored_origin():
    # Centimetre coordinates on the edges of 1.6 m bins (a cell that divides 240 m), in
    # the local coordinates of two blocks of one tile whose anchored origins differ by
    # 240 m: each point lies in the same absolute bin (the one whose lower edge it is on).
    # Before: (y - y0) / cell rounded either way, 2499 of samp11's 38010 points binned
    # otherwise in a block above the tile's 240 m line than in the whole tile.
    cell = 1.6
    edges = np.round(np.arange(118, 300) * cell, 2)  # 188.8 ... 478.4 m, on edges
    for shift in (0.0, 240.0):
        y = edges - shift
        g = Grid.covering(np.zeros(y.size), y, cell)
        absolute = g.index(np.zeros(y.size), y) // g.nx + round((g.y0 + shift) / cell)
        assert np.array_equal(absolute, np.arange(118, 300))


def test_grow_phases_moves_fewer_labels_under_a_translation_and_nothing_without_growth():
    # Growth's nodes are the lowest points of the final bins, so whether it reaches a
    # crest hangs on where the bin edges fall. ``grow_phases=2`` runs growth over 2 × 2
    # offsets of those bins within each voted phase and votes their shares: a translation
    # by a fraction of a bin moves fewer labels (9 of 16 124 here, against 25 with one
    # growth). Without growth the option changes nothing. Bins on multiples of the cell,
    # so that they move with the translation (data-anchored bins do not).
    sparse = make_scene(size=120.0, density=1.0, seed=1).xyz
    p = nist.NistParams(rough_k=0, density=1.0, bin_anchor="absolute")
    moves = (np.array([1.3, 0.4, 0.0]), np.array([2.1, 2.9, 0.0]))

    def moved(q: nist.NistParams) -> int:
        base = nist.classify_ground(sparse, q)
        return sum(
            int(np.count_nonzero(base != nist.classify_ground(sparse + m, q))) for m in moves
        )

    one, four = moved(p), moved(p.model_copy(update={"grow_phases": 2}))
    assert four < one / 2
    off = p.model_copy(update={"grow": False})
    assert np.array_equal(
        nist.classify_ground(sparse, off),
        nist.classify_ground(sparse, off.model_copy(update={"grow_phases": 2})),
    )


def test_data_anchored_bins_label_a_translated_tile_alike():
    """With ``bin_anchor="data"`` a bin corner sits at the centre of the data's bounds,
    so a sparse tile moved by a few metres (not a multiple of any bin) labels point for
    point as it did, and a quarter turn about its centre nearly so (only ties of equal
    heights and points on bin edges may go another way); with a given ``anchor`` (a
    job's), blocks cut from it bin alike."""
    sc = make_scene(100, 0.6, seed=11)
    xyz = sc.xyz + np.array([512_000.37, 5_403_000.81, 0.0])
    params = nist.NistParams(bin_anchor="data")
    ground = nist.classify_ground(xyz, params)
    for dx, dy in ((3.3, 21.1), (0.7, 0.0)):
        moved = nist.classify_ground(xyz + np.array([dx, dy, 0.0]), params)
        assert np.array_equal(moved, ground), (dx, dy, np.count_nonzero(moved != ground))
    c = (xyz[:, :2].min(axis=0) + xyz[:, :2].max(axis=0)) / 2
    turned = np.column_stack([c[0] - (xyz[:, 1] - c[1]), c[1] + (xyz[:, 0] - c[0]), xyz[:, 2]])
    assert np.count_nonzero(nist.classify_ground(turned, params) != ground) <= 0.001 * len(xyz)
    given = nist.classify_ground(xyz, params.model_copy(update={"anchor": (c[0], c[1])}))
    assert np.array_equal(given, ground)


def test_growth_drops_a_deep_low_outlier_it_reached_at_the_edge_of_the_data():
    """``grow_low``: at this bin phase growth reaches a return 4.4 m under the ground at
    the edge of the data (the bend allowed over a long edge along the hull); a grown node
    that far below its ground neighbours is a low outlier, as screening judges one."""
    sc = make_scene(150, 1.0, seed=7)
    depth = sc.surface(sc.xyz[:, 0], sc.xyz[:, 1]) - sc.xyz[:, 2]
    deep = (sc.truth == 7) & (depth > 2.0)
    p = nist.NistParams(bin_anchor="data", grow_low=False)
    assert nist.classify_ground(sc.xyz, p)[deep].any()
    assert not nist.classify_ground(sc.xyz, p.model_copy(update={"grow_low": True}))[deep].any()
