"""The grid method's compiled kernels give the numpy expressions they replace to the bit."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.workers import mixed_grid, scan_geometry
from terrasift.workers._mixed_kernels import continued, incidence_cos, line_gather, spread_of


def _ranges(rng: np.random.Generator, n: int) -> np.ndarray:
    """Ranges with the NaNs of missing beams, some equal pairs and some far apart."""
    r = rng.uniform(2.0, 40.0, n)
    r[rng.random(n) < 0.1] = np.nan
    r[::17] = r[::17].round(1)
    return r


def test_spread_continued_and_incidence_match_numpy() -> None:
    rng = np.random.default_rng(3)
    n = 5000
    r, ra, rb = (_ranges(rng, n) for _ in range(3))
    va, vb = 1.0 / ra, 1.0 / rb
    vb[::23] = va[::23]  # a flat surface: no change per beam
    va[::29] = -1e-3  # the surface continued past the horizon
    across = np.abs(rng.normal(0.0, 0.05, n))
    across[::13] = np.nan
    blur = rng.uniform(0.0, 0.4, n)
    sigma, sigmas, step, step_x = 0.004, 4.0, np.radians(0.05), np.radians(0.07)
    for i in (0, 1, 3):
        factor = np.sqrt((1 + i) ** 2 + i**2 + 1)
        slope = np.abs(ra - rb)
        old = sigmas * np.sqrt(sigma**2 + (np.nan_to_num(slope) * blur) ** 2) * factor
        assert np.array_equal(spread_of(slope, blur, sigma**2, sigmas, factor), old)
        with np.errstate(invalid="ignore", divide="ignore"):
            v = va + (va - vb) * float(i)
            old_c = np.where(v > 0, 1.0 / v, np.inf)
        assert np.array_equal(continued(va, vb, float(i)), old_c)
    with np.errstate(invalid="ignore"):
        tan_a = r * np.abs(va - vb) / step
        tan_x = r * across / ra**2 / step_x
        old_i = 1.0 / np.sqrt(1.0 + tan_a**2 + tan_x**2)
    assert np.array_equal(incidence_cos(r, va, vb, across, ra, step, step_x), old_i, equal_nan=True)


@pytest.mark.parametrize("dense", [True, False])
def test_line_matches_lookups_one_offset_at_a_time(dense: bool) -> None:
    """Every offset's neighbour (the dense table's last of equal keys, the search's
    first), range, inverse range and change across, as the lookups one by one gave."""
    rng = np.random.default_rng(5)
    n_e, n_a = 40, 60
    ia = rng.integers(10, n_a - 10, 1500)
    ie = rng.integers(10, n_e - 10, 1500)
    key = np.sort(ia * n_e + ie)  # repeats: two returns on one beam
    n = key.size
    r_pad = np.append(_ranges(rng, n), np.nan)
    across = np.abs(rng.normal(0.0, 0.05, n))
    n_cells = n_a * n_e if dense else 17 * n * n_a * n_e
    find = mixed_grid._finder(key, n_cells)
    assert (find.lut.size > 0) == dense
    inv_pad, c_pad = 1.0 / r_pad, np.append(across, 0.0)
    for stride in (1, n_e):
        line = mixed_grid._Line(key, r_pad, find, stride, 4, across)
        again = mixed_grid._Line(key, r_pad, find, stride, 4, across, reuse=line)
        for o in (-4, -3, -2, -1, 1, 2, 3, 4):
            want = key + o * stride
            if dense:
                lut = np.full(n_cells, n, dtype=np.int64)
                lut[key] = np.arange(n)
                j = lut[want]
            else:
                j = np.minimum(np.searchsorted(key, want), n - 1)
                j = np.where(key[j] == want, j, n)
            for got in (line, again):
                assert np.array_equal(got.J[o], j)
                assert np.array_equal(got.R[o], r_pad[j], equal_nan=True)
                assert np.array_equal(got.V[o], inv_pad[j], equal_nan=True)
                assert np.array_equal(got.C[o], c_pad[j])
        assert again.buffers[1] is line.buffers[1]  # the memory taken over
    # one kernel call does all offsets: the same as asking for them one by one
    offs = np.array([1, -1, 2, -2], dtype=np.int64)
    J = np.empty((2, n), dtype=np.int64)
    R, V, C = (np.empty((4, n)) for _ in range(3))
    line_gather(key, find.lut, offs, r_pad, inv_pad, c_pad, J, R, V, C)
    assert np.array_equal(J[1], find(key - 1))
    assert np.array_equal(R[3], r_pad[find(key - 2)], equal_nan=True)


def test_coordinate_scale_and_reused_tree_as_before() -> None:
    rng = np.random.default_rng(7)
    xyz = np.round(rng.uniform(-30.0, 30.0, (20_000, 3)) / 0.001) * 0.001
    xyz[::5] = xyz[1::5]  # repeated coordinates
    for data in (xyz, xyz + rng.normal(0.0, 1e-4, xyz.shape)):  # quantised, then not

        def by_unique(v: np.ndarray) -> np.ndarray:
            d = np.diff(np.unique(v))
            return d[d > 1e-9]

        def by_sort(v: np.ndarray) -> np.ndarray:
            d = np.diff(np.sort(v))
            return d[d > 1e-9]

        for col in range(3):  # the differences coordinate_scale reads, as before
            assert np.array_equal(by_sort(data[:, col]), by_unique(data[:, col]))
    assert scan_geometry.coordinate_scale(xyz) == pytest.approx(0.001)
    az, el = rng.uniform(-0.3, 0.3, 3000), rng.uniform(-0.2, 0.1, 3000)
    first = scan_geometry._neighbours(az, el, k=8)
    assert scan_geometry._neighbours(az, el, k=12)[1].shape[1] == 12
    again = scan_geometry._neighbours(az.copy(), el.copy(), k=8)  # the tree reused
    for a, b in zip(first, again, strict=True):
        assert np.array_equal(a, b)
    other = scan_geometry._neighbours(az[::-1].copy(), el[::-1].copy(), k=8)
    assert not np.array_equal(other[1], first[1])  # other points: a tree of their own
