"""Terrain gauges (NIST §5): slope, roughness, pitch and roll on surfaces with exact gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rasterio.transform import Affine

from terrasift.errors import ParameterError
from terrasift.synthetic.forest import AnalyticSurface, raster_of, sinusoid, tilted_plane
from terrasift.workers.bins import Grid
from terrasift.workers.registry import stages
from terrasift.workers.terrain import (
    Roughness,
    TerrainParams,
    combine,
    line_coordinates,
    median_smooth,
    path_profile,
    roughness,
    slope_degrees,
)

X0, Y0 = 500_000.0, 5_400_000.0


def _cloud(
    surface, nx: int, ny: int, x0: float = X0, y0: float = Y0, density: float = 30.0, seed: int = 0
):
    """Uniform points over nx × ny metres from (x0, y0); z from ``surface`` on local coordinates."""
    rng = np.random.default_rng(seed)
    n = int(nx * ny * density)
    u, v = rng.uniform(0, nx, n), rng.uniform(0, ny, n)
    return np.column_stack([u + x0, v + y0, surface(u, v)])


# ---------------------------------------------------------------- roughness


@pytest.mark.parametrize(("gx", "gy"), [(0.0, 0.0), (0.3, -0.2), (-1.2, 0.8), (2.0, 0.05)])
def test_roughness_is_zero_on_any_plane(gx, gy):
    xyz = _cloud(AnalyticSurface(300.0, gx, gy), 30, 20, seed=int(10 * abs(gx)))
    r = roughness(xyz, Grid(X0, Y0, 1.0, 30, 20))
    assert r.n_bins == 600  # steep smooth bins are accepted (RMS about the plane)
    assert r.roughness < 1e-9
    assert r.mean_sx == pytest.approx(gx) and r.mean_sy == pytest.approx(gy)


def test_roughness_is_positive_off_a_plane():
    xyz = _cloud(sinusoid(), 40, 40)
    r = roughness(xyz, Grid(X0, Y0, 1.0, 40, 40))
    assert r.n_bins > 1000 and r.roughness > 0.05
    assert r.roughness == pytest.approx(math.hypot(r.xslope_rms, r.yslope_rms))


def test_roughness_union_of_two_areas_with_the_same_value():
    # Area A: crossing sinusoids. Area B, beside it: different bumps and another
    # point pattern, scaled and tilted so its gauge and mean slope equal A's.
    ga = Grid(X0, Y0, 1.0, 30, 30)
    gb = Grid(X0 + 30, Y0, 1.0, 30, 30)
    a = _cloud(sinusoid(), 30, 30, seed=1)
    ra = roughness(a, ga)

    def bumps(u, v):
        return 0.8 * np.sin(u / 3.1) * np.cos(v / 4.3) + 0.3 * np.sin((u + 2 * v) / 5.0)

    b0 = _cloud(bumps, 30, 30, x0=X0 + 30, density=12.0, seed=2)
    rb0 = roughness(b0, gb)
    lam = ra.roughness / rb0.roughness
    tx, ty = ra.mean_sx - lam * rb0.mean_sx, ra.mean_sy - lam * rb0.mean_sy
    b = b0.copy()
    b[:, 2] = lam * b0[:, 2] + tx * (b0[:, 0] - X0) + ty * (b0[:, 1] - Y0)
    rb = roughness(b, gb)
    assert rb.n_bins == rb0.n_bins  # scaling kept every bin's plane fit acceptable
    assert rb.roughness == pytest.approx(ra.roughness, rel=1e-9)
    assert rb.xslope_rms != pytest.approx(ra.xslope_rms, rel=1e-3)  # not the same area twice

    union = roughness(np.vstack([a, b]), Grid(X0, Y0, 1.0, 60, 30))
    assert union.n_bins == ra.n_bins + rb.n_bins
    assert union.roughness == pytest.approx(ra.roughness, rel=1e-9)


def test_roughness_blocks_combine_exactly():
    xyz = _cloud(sinusoid(), 50, 40, seed=5)
    whole = roughness(xyz, Grid(X0, Y0, 1.0, 50, 40))
    parts = [roughness(xyz, Grid(X0 + x, Y0 + y, 1.0, 25, 20)) for x in (0, 25) for y in (0, 20)]
    merged = combine(parts)
    assert merged.n_bins == whole.n_bins
    for k in ("roughness", "xslope_rms", "yslope_rms", "mean_sx", "mean_sy"):
        assert getattr(merged, k) == pytest.approx(getattr(whole, k), rel=1e-12)


def test_two_planes_are_not_a_plane():
    # The seed's two properties cannot both hold: each half of a roof is a plane
    # (gauge 0), the roof is not. The gauge says so.
    left = _cloud(AnalyticSurface(0.0, 0.4, 0.0), 20, 20)
    right = _cloud(AnalyticSurface(8.0, -0.4, 0.0), 20, 20, x0=X0 + 20)
    rl, rr = (
        roughness(left, Grid(X0, Y0, 1.0, 20, 20)),
        roughness(right, Grid(X0 + 20, Y0, 1.0, 20, 20)),
    )
    assert rl.roughness < 1e-9 and rr.roughness < 1e-9
    assert combine([rl, rr]).roughness == pytest.approx(0.4)


def test_roughness_rejects_rough_and_sparse_bins():
    rng = np.random.default_rng(3)
    xyz = _cloud(AnalyticSurface(0.0, 0.1, 0.1), 10, 10)
    spike = xyz[::50].copy()
    spike[:, 2] += rng.uniform(2, 5, spike.shape[0])  # vegetation on top: bins rejected by RMS
    r = roughness(np.vstack([xyz, spike]), Grid(X0, Y0, 1.0, 10, 10))
    assert r.n_bins < 100 and r.roughness < 1e-9
    assert roughness(xyz[:5], Grid(X0, Y0, 1.0, 10, 10)).n_bins == 0
    assert math.isnan(Roughness.from_slopes([], []).roughness)
    assert Roughness.from_slopes([], []).to_dict()["roughness"] is None


# ---------------------------------------------------------------- slope


def test_slope_on_a_plane_is_exact_everywhere_with_holes():
    surf = tilted_plane(0.3, -0.4)
    dtm, _ = raster_of(surf, 0.0, 50.0, 0.5, 80, 100)
    dtm[40:45, 30:33] = np.nan
    dtm[0, 0] = np.nan
    s = slope_degrees(dtm, 0.5)
    expect = math.degrees(math.atan(0.5))
    assert np.isnan(s[40:45, 30:33]).all() and np.isnan(s[0, 0])
    np.testing.assert_allclose(s[np.isfinite(dtm)], expect, atol=1e-9)
    for smooth in ("dtm", "gradient"):
        np.testing.assert_allclose(
            slope_degrees(dtm, 0.5, 5, smooth)[np.isfinite(dtm)], expect, atol=1e-9
        )


def test_slope_on_a_sinusoid_and_median_removes_a_spike():
    surf = sinusoid()
    dtm, _ = raster_of(surf, 0.0, 120.0, 1.0, 120, 120)
    xs = np.arange(120) + 0.5
    gx, gy = surf.gradient(*np.meshgrid(xs, 120.0 - xs))
    truth = np.degrees(np.arctan(np.hypot(gx, gy)))
    s = slope_degrees(dtm, 1.0)
    assert np.abs(s - truth)[2:-2, 2:-2].max() < 0.5
    spiked = dtm.copy()
    spiked[60, 60] += 3.0
    assert (
        abs(median_smooth(spiked, 3)[60, 60] - dtm[60, 60]) < 0.1
    )  # neighbours differ by up to 0.3 m
    assert np.abs(slope_degrees(spiked, 1.0) - truth)[2:-2, 2:-2].max() < 1.0
    assert np.abs(slope_degrees(spiked, 1.0, median_size=1) - truth)[2:-2, 2:-2].max() > 30


# ---------------------------------------------------------------- pitch and roll


def _expected(surf, pp, line):
    seg = np.diff(line, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    k = np.clip(
        np.searchsorted(np.r_[0, np.cumsum(length)], pp.distance, "right") - 1, 0, len(seg) - 1
    )
    tx, ty = seg[k, 0] / length[k], seg[k, 1] / length[k]
    zx, zy = surf.gradient(pp.x - X0, pp.y - Y0)
    return np.degrees(np.arctan(tx * zx + ty * zy)), np.degrees(np.arctan(ty * zx - tx * zy))


LINE = np.array(
    [[X0 + 20, Y0 + 30], [X0 + 180, Y0 + 70], [X0 + 120, Y0 + 180], [X0 + 30, Y0 + 150]]
)


@pytest.mark.parametrize(("surf", "tol"), [(tilted_plane(0.12, -0.07), 1e-9), (sinusoid(), 0.5)])
def test_pitch_and_roll_match_the_analytic_gradient(surf, tol):
    dtm, tr = raster_of(lambda x, y: surf(x - X0, y - Y0), X0, Y0 + 200, 1.0, 200, 200)
    pp = path_profile(dtm, tr, LINE, 0.7)
    pitch, roll = _expected(surf, pp, LINE)
    assert np.abs(pp.pitch_deg - pitch).max() <= tol
    assert np.abs(pp.roll_deg - roll).max() <= tol
    assert np.abs(pitch).max() > 3 and np.abs(roll).max() > 3  # the test has something to measure
    np.testing.assert_allclose(pp.z, surf(pp.x - X0, pp.y - Y0), atol=0.01)


def test_pitch_and_roll_signs():
    # Ground rising to the east and to the south; drive east.
    surf = AnalyticSurface(0.0, 0.1, -0.2)
    dtm, tr = raster_of(surf, 0.0, 50.0, 1.0, 50, 50)
    pp = path_profile(dtm, tr, np.array([[5.0, 25.0], [45.0, 25.0]]), 5.0)
    np.testing.assert_allclose(pp.pitch_deg, math.degrees(math.atan(0.1)))  # uphill: positive
    np.testing.assert_allclose(pp.roll_deg, math.degrees(math.atan(0.2)))  # s = t × ẑ points south
    back = path_profile(dtm, tr, np.array([[45.0, 25.0], [5.0, 25.0]]), 5.0)
    np.testing.assert_allclose(back.pitch_deg, -pp.pitch_deg)
    np.testing.assert_allclose(back.roll_deg, -pp.roll_deg)


def test_profile_spacing_nodata_and_outputs():
    surf = tilted_plane()
    dtm, tr = raster_of(surf, 0.0, 40.0, 1.0, 40, 40)
    dtm[:, 20:22] = np.nan
    line = np.array(
        [[2.0, 2.0], [2.0, 2.0], [30.0, 2.0], [30.0, 60.0]]
    )  # repeated vertex; leaves the DTM
    pp = path_profile(dtm, tr, line, 3.0)
    assert pp.distance[0] == 0 and pp.distance[-1] == pytest.approx(86.0)
    np.testing.assert_allclose(np.diff(pp.distance[:-1]), 3.0)
    assert np.isnan(pp.z[pp.y > 40]).all() and np.isfinite(pp.z[pp.y < 39]).sum() > 10
    hole = (pp.x > 19) & (pp.x < 23) & (pp.y < 3)
    assert hole.any() and np.isnan(pp.z[hole]).all()
    recs = pp.to_records()
    assert len(recs) == pp.distance.size and set(recs[0]) == {
        "distance",
        "x",
        "y",
        "z",
        "pitch_deg",
        "roll_deg",
    }
    assert recs[-1]["z"] is None
    csv = pp.to_csv().splitlines()
    assert csv[0] == "distance,x,y,z,pitch_deg,roll_deg" and len(csv) == pp.distance.size + 1
    with pytest.raises(ParameterError):
        path_profile(dtm, tr, np.array([[1.0, 1.0], [1.0, 1.0]]), 1.0)
    with pytest.raises(ParameterError):
        path_profile(dtm, tr, line, 0.0)
    with pytest.raises(ParameterError):
        path_profile(dtm, Affine(1, 0.2, 0, 0, -1, 40), line, 1.0)


def test_line_coordinates_from_wgs84():
    from pyproj import Transformer

    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True)
    lonlat = [[9.10, 48.70], [9.12, 48.71], [9.13, 48.69]]
    feature = {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": lonlat},
        "properties": {},
    }
    xy = line_coordinates(feature, "EPSG:32632")
    ex, ey = to_utm.transform([p[0] for p in lonlat], [p[1] for p in lonlat])
    np.testing.assert_allclose(xy, np.column_stack([ex, ey]), atol=1e-6)
    native = {"type": "LineString", "coordinates": [[500000, 5400000, 3], [500100, 5400000, 4]]}
    np.testing.assert_array_equal(
        line_coordinates(native, "EPSG:32632", src_crs="EPSG:32632"),
        [[500000, 5400000], [500100, 5400000]],
    )
    for bad in (
        {"type": "Point", "coordinates": [1, 2]},
        {"type": "LineString", "coordinates": [[1, 2]]},
    ):
        with pytest.raises(ParameterError):
            line_coordinates(bad, "EPSG:32632")


def test_terrain_params():
    with pytest.raises(ParameterError):
        TerrainParams.preset(median_size=4)
    assert TerrainParams().cell == 1.0
    assert any(s.id == "terrain" and s.run is roughness for s in stages())


def test_median_smooth_is_the_window_median_where_the_window_is_full():
    rng = np.random.default_rng(4)
    z = rng.normal(size=(40, 50))
    z[rng.random(z.shape) < 0.08] = np.nan
    for size in (3, 5):
        out = median_smooth(z, size)
        r = size // 2
        for i, j in [(0, 0), (r, r), (10, 17), (39, 49), (20, 25), (5, 44)]:
            win = z[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1]
            full = win.shape == (size, size) and np.isfinite(win).all()
            expected = np.median(win) if full else z[i, j]
            assert np.array_equal(out[i, j], expected, equal_nan=True), (size, i, j)
        assert np.isnan(out[np.isnan(z)]).all()
