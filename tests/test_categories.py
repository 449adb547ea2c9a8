"""Category fit on analytic surfaces with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.errors import ParameterError
from terrasift.workers.categories import (
    _POINTS,
    EDGES,
    NODATA,
    CategoryParams,
    category_grids,
    compute_categories,
    regional_gradient,
)

CELL = 0.5
K = 4  # cells per 2 m tile


def grid(tiles: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centre coordinates (x east, y north) of a north-up DTM, ``tiles`` × ``tiles`` tiles."""
    n = tiles * K
    c = (np.arange(n) + 0.5) * CELL
    return np.meshgrid(c, -c)


@pytest.mark.parametrize("code", range(1, 9))
def test_plane_in_each_direction_gives_that_inclination(code):
    x, y = grid()
    a = np.radians(45 * (code - 1))
    z = 0.32 * (x * np.cos(a) + y * np.sin(a)) + 50
    cats = compute_categories(z, CELL, CategoryParams())
    assert (cats.inclination == code).all()
    assert (cats.orientation == 0).all() and (cats.state == 0).all()
    # rise of the plane over the cell centres of one tile, in decimetres
    span = 0.32 * 1.5 * (abs(np.cos(a)) + abs(np.sin(a)))
    assert np.allclose(cats.height10, np.round(span * 10))


def test_flat_and_nearly_flat_tiles_are_all_zero():
    x, y = grid()
    rng = np.random.default_rng(1)
    z = 10 + 0.02 * x + rng.normal(0, 0.01, x.shape)
    cats = compute_categories(z, CELL)
    for band in (cats.inclination, cats.orientation, cats.state):
        assert (band == 0).all()


@pytest.mark.parametrize("sigma", [0.01, 0.03, 0.05])
def test_noise_is_measured_and_does_not_unflatten_level_ground(sigma):
    x, y = grid(20)
    rng = np.random.default_rng(3)
    z = 10 + 0.03 * x + rng.normal(0, sigma, x.shape)
    cats = compute_categories(z, CELL)
    assert cats.noise == pytest.approx(sigma, rel=0.15)
    assert (cats.inclination == 0).mean() > 0.97
    assert (cats.state == 0).mean() > 0.97
    seed = compute_categories(z, CELL, CategoryParams(noise=0))
    if sigma >= 0.05:  # the seed's max - min sees the noise
        assert (seed.inclination == 0).mean() < 0.8
    # a real slope stays inclined under the same noise
    steep = compute_categories(z + 0.25 * y, CELL)
    assert (steep.inclination == 3).mean() > 0.97


def test_overlapping_tiles_every_step():
    x, y = grid(6)
    z = np.where(x > 4.0, 0.4, 0.0)  # a step on the border of two 2 m tiles
    assert (compute_categories(z, CELL).height10 == 0).all()  # split: neither sees it
    cats = compute_categories(z, CELL, step=1.0)
    assert cats.shape == (12, 12) and cats.spacing == 1.0
    t = cats.transform(__import__("rasterio").Affine(CELL, 0, 0, 0, -CELL, 0))
    assert (t.a, t.c) == (1.0, 0.5)  # tile i stands for the metre at its centre
    # the tile starting at 3 m holds the whole step
    assert (cats.height10[:11, 3] == 4).all() and (cats.height10[11] == NODATA).all()
    assert (np.delete(cats.height10[:11, :11], 3, axis=1) == 0).all()


def test_gentle_slope_below_flat_height_is_flat_but_steeper_is_not():
    x, y = grid()
    gentle = compute_categories(0.1 * y, CELL)  # 0.15 m over a tile's cell centres
    steep = compute_categories(0.2 * y, CELL)  # 0.30 m
    assert (gentle.inclination == 0).all()
    assert (steep.inclination == 3).all()
    rough = compute_categories(0.1 * y, CELL, CategoryParams(flat_height=0.1))
    assert (rough.inclination == 3).all()


def hinge_tile(code: int, depth: float) -> np.ndarray:
    """One 2 m tile (4 × 4 cells) shaped as two planes meeting along edge ``code``."""
    half = K * CELL / 2
    c = (np.arange(K) + 0.5) * CELL - half
    x, y = np.meshgrid(c, -c)
    pa, pb = (np.array(_POINTS[d], float) * half for d in divmod(code, 10))
    t = pb - pa
    n = np.array([-t[1], t[0]]) / np.hypot(*t)
    d = np.abs((x - pa[0]) * n[0] + (y - pa[1]) * n[1])
    return depth * d


@pytest.mark.parametrize("code", EDGES)
@pytest.mark.parametrize("shape, state", [("V", 2), ("Λ", 1)])
def test_v_and_lambda_edges_in_every_orientation(code, shape, state):
    sign = 1.0 if shape == "V" else -1.0
    z = 100 + hinge_tile(code, sign * 0.6)
    cats = compute_categories(z, CELL)
    assert cats.shape == (1, 1)
    assert cats.orientation[0, 0] == code
    assert cats.state[0, 0] == state
    if code in (15, 37, 26, 48):  # symmetric in the tile: the mean plane is level
        assert cats.inclination[0, 0] == 0


def test_off_centre_edge_keeps_the_inclination_of_its_larger_plane():
    # a V whose bottom runs along the tile's west quarter: the east plane dominates
    half = K * CELL / 2
    c = (np.arange(K) + 0.5) * CELL - half
    x, _ = np.meshgrid(c, -c)
    z = 0.8 * np.abs(x + 0.5)
    cats = compute_categories(z, CELL)
    assert cats.state[0, 0] == 2 and cats.orientation[0, 0] == 37
    assert cats.inclination[0, 0] == 1


def test_edge_with_a_dominant_slope_along_it_is_an_extreme_point():
    # a gully falling steeply to the south: concave, lowest at the south midpoint
    z = hinge_tile(37, 0.3)
    half = K * CELL / 2
    c = (np.arange(K) + 0.5) * CELL - half
    _, y = np.meshgrid(c, -c)
    cats = compute_categories(z + 0.6 * y, CELL)
    assert cats.state[0, 0] == 2 and cats.orientation[0, 0] == 77
    # the same as a spur (convex): highest at the north midpoint
    cats = compute_categories(-z + 0.6 * y, CELL)
    assert cats.state[0, 0] == 1 and cats.orientation[0, 0] == 33


def test_rotating_the_dtm_turns_every_direction():
    rng = np.random.default_rng(3)
    x, y = grid(8)
    z = (
        2 * np.sin(x / 3)
        + 1.5 * np.cos(y / 4)
        + 0.4 * np.abs(x - 7.3)
        + rng.normal(0, 0.01, x.shape)
    )
    a = compute_categories(z, CELL)
    b = compute_categories(np.rot90(z), CELL)  # contents turned 90° counter-clockwise
    inc_a = np.rot90(a.inclination)
    turned = np.where(inc_a > 0, (inc_a + 1) % 8 + 1, 0)
    assert (b.inclination == turned).mean() > 0.95
    assert (b.state == np.rot90(a.state)).mean() > 0.95


def test_nodata_and_partial_tiles_are_marked():
    x, y = grid(3)
    z = 0.3 * x
    z[5, 5] = np.nan  # tile (1, 1)
    z = np.pad(z, ((0, 2), (0, 0)), constant_values=1.0)  # a partial tile row at the bottom
    cats = compute_categories(z, CELL)
    assert cats.shape == (4, 3)
    for band in cats.bands():
        assert band[1, 1] == NODATA
        assert (band[3] == NODATA).all()
    assert cats.nodata.sum() == 4


def test_tile_size_snaps_to_cells_and_transform_scales():
    from rasterio import Affine

    x, y = grid(4)
    cats = compute_categories(0.3 * x, CELL, CategoryParams(tile_size=3.0))
    assert cats.cells_per_tile == 6 and cats.tile_size == 3.0
    t = cats.transform(Affine(CELL, 0, 1000, 0, -CELL, 2000))
    assert (t.a, t.e, t.c, t.f) == (3.0, -3.0, 1000, 2000)
    with pytest.raises(ParameterError):
        compute_categories(0.3 * x, 2.0, CategoryParams(tile_size=0.5))


def test_parameters_are_validated():
    with pytest.raises(ParameterError):
        CategoryParams.preset("default", flat_height=-1)
    assert CategoryParams.preset("rough").flat_height == 0.3


def test_regional_slope_shows_a_ditch_on_a_slope_and_leaves_a_bend_a_bend():
    """A 3 m ditch across a 15 % slope: on its regional slope (median tile gradient
    over 24 m) the slope is level, the uphill bank falls and the downhill one
    rises. A bend from level ground to a 33 % flank stays one concave tile between
    level tiles (the window's least-squares plane would leave a dip with banks)."""
    cell, n = 0.5, 160
    x = (np.arange(n) + 0.5) * cell
    ditch = -0.5 * np.clip(1 - np.abs(x - 40) / 1.5, 0, None)
    z = np.tile(0.15 * x + ditch, (n, 1))  # rises east
    p = CategoryParams(noise=0)
    raw = compute_categories(z, cell, p, step=1.0)
    trend = regional_gradient(z, cell, p, 24.0, step=1.0)
    assert np.allclose(trend[0][10:-10, 10:-10], 0.15, atol=1e-6)
    on_slope = compute_categories(z, cell, p, step=1.0, trend=trend)
    row_raw, row = raw.inclination[40, 30:50], on_slope.inclination[40, 30:50]
    assert (row_raw[:5] == 1).all()  # the raw slope rises east
    assert np.isin(row, (4, 5, 6)).any() and np.isin(row, (8, 1, 2)).any()
    assert (on_slope.inclination[40, 5:30] == 0).all()  # the slope itself is level
    bend = np.tile(0.33 * np.clip(x - 40, 0, None), (n, 1))
    cats = compute_categories(bend, cell, p, 1.0, regional_gradient(bend, cell, p, 24.0, 1.0))
    # only the bend's own tile (a concave edge) is not level: no banks either side of it
    assert np.count_nonzero(cats.inclination[40, :-1]) == 1 and cats.state[40, 39] == 2


def test_regional_gradient_of_a_window_one_tile_thin_is_its_plane():
    """A wide window sampled every few tiles (120 m: every 3rd 2 m tile) over a DTM only
    one or two tiles thin along an axis (a feature search's window cut at the DTM's
    edge) takes its samples from the tiles it has: the plane's gradient, no error."""
    cell = 0.5
    p = CategoryParams(noise=0)
    for shape in ((4, 400), (400, 4), (4, 4), (8, 400)):
        y, x = np.mgrid[0 : shape[0], 0 : shape[1]] * cell
        gx, gy = regional_gradient(0.12 * x - 0.05 * y, cell, p, 120.0)
        assert gx.shape == (shape[0] // 4, shape[1] // 4)
        assert np.allclose(gx, 0.12, atol=1e-9) and np.allclose(gy, 0.05, atol=1e-9), shape


def test_grids_of_one_step_share_their_fits_and_match_separate_runs():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:80, 0:80] * 0.5
    z = 0.12 * x + 0.3 * np.sin(y / 3) + rng.normal(0, 0.02, x.shape)
    p = CategoryParams(noise=0.02)
    trend = regional_gradient(z, 0.5, p, 24.0, 1.0)
    both = category_grids(z, 0.5, p, 1.0, [None, trend])
    for got, want in zip(
        both,
        (compute_categories(z, 0.5, p, 1.0), compute_categories(z, 0.5, p, 1.0, trend)),
        strict=True,
    ):
        assert (got.bands() == want.bands()).all()
    assert not (both[0].inclination == both[1].inclination).all()


def test_compiled_tile_fit_matches_least_squares_on_every_tile():
    """The one-pass fit gives each tile's plane, its best hinge model and its heights as
    separate least-squares fits do (one plane; one plane plus |distance to each edge|)."""
    from terrasift.workers._category_kernels import fit_tiles
    from terrasift.workers.categories import _cell_coords, _models

    k, cell = 4, 0.5
    rng = np.random.default_rng(5)
    dtm = rng.normal(0, 0.3, (3 * k, 5 * k)) + np.linspace(0, 2, 5 * k)
    dtm[0, 0] = np.nan  # tile 0 has no data
    xs, ys = _cell_coords(k, cell)
    _, _, h, hnorm, _ = _models(k, cell)
    trend = np.zeros((1, 2, 15))
    trend[0, 0], trend[0, 1] = 0.1, -0.2
    # every tile tries two planes and takes them; every model explains its tile
    nodata, two, best, c3, gx, gy, height, relief, lying = fit_tiles(
        dtm, k, k, 3, 5, xs, ys, h, hnorm, 0.0, 1.0, np.inf, trend
    )
    assert nodata[0] and not nodata[1:].any() and two[1:].all()
    a0 = np.column_stack([np.ones(k * k), xs, ys])
    tilt = 0.1 * xs - 0.2 * ys
    for t in range(1, 15):
        r, q = divmod(t, 5)
        z = dtm[r * k : (r + 1) * k, q * k : (q + 1) * k].ravel()
        coef, *_ = np.linalg.lstsq(a0, z, rcond=None)
        assert np.isclose(gx[0, t], coef[1] - 0.1) and np.isclose(gy[0, t], coef[2] + 0.2)
        fits = []
        for e in range(16):  # h[:, e]: |distance to edge e| with its plane part removed
            a = np.column_stack([a0, h[:, e]])
            sol, *_ = np.linalg.lstsq(a, z, rcond=None)
            fits.append((((z - a @ sol) ** 2).sum(), sol[3], a @ sol))
        e = int(np.argmin([f[0] for f in fits]))
        assert best[t] == e and np.isclose(c3[t], fits[e][1])
        assert np.isclose(height[0, t], np.ptp(z - tilt))
        assert np.isclose(relief[0, t], np.ptp(fits[e][2] - tilt))
        assert np.isclose(lying[t], np.ptp(fits[e][2]))


def test_grade_counts_a_tile_slope_in_whole_multiples_of_the_slope_noise():
    """``grade``: the plane's gradient over the DTM's slope noise σ_g, rounded down; every
    gradient is 254 when the noise tests are off (σ_g 0); nodata tiles 255."""
    from terrasift.workers.categories import CategoryParams, compute_categories

    cell = 0.5
    x = np.tile((np.arange(80) + 0.5) * cell, (40, 1))
    z = np.where(x < 20, 0.05 * x, 1.0)  # 5 % rising east, then level
    z[0, -1] = np.nan
    cats = compute_categories(z, cell, CategoryParams(noise=0.001, slope_noise=0.006))
    assert cats.grade is not None
    assert (cats.grade[:, :9] == 8).all()  # 0.05 / 0.006 = 8.3
    assert (cats.grade[1:, 11:] == 0).all()
    assert cats.grade[0, -1] == 255
    off = compute_categories(z, cell, CategoryParams(noise=0, slope_noise=0))
    assert off.grade is not None
    assert (off.grade[:, :9] == 254).all() and (off.grade[1:, 11:] == 0).all()
