"""The grid method's compiled kernels give the numpy expressions they replace to the bit."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.workers import mixed_grid, scan_geometry
from terrasift.workers._mixed_kernels import anchor_pass, behind_both, line_gather, spread_of


def _ranges(rng: np.random.Generator, n: int) -> np.ndarray:
    """Ranges with the NaNs of missing beams, some equal pairs and some far apart."""
    r = rng.uniform(2.0, 40.0, n)
    r[rng.random(n) < 0.1] = np.nan
    r[::17] = r[::17].round(1)
    return r


def _anchor_numpy(r, R, V, C, blur, i, k, off_end, met, off_blend):
    """The numpy passes ``anchor_pass`` replaces, beam offset ``i`` on side +1 (``k``:
    the settings as the kernel takes them), updating the three arrays in place."""
    (sigma2, sigmas, spread0, f1, fi, fit3, flat_tol, c3scale, margin) = k[:9]
    step, step_x, across, max_gap, half = k[9:]
    a, a1, a2 = i, i + 1, i + 2
    ra = R[a]
    with np.errstate(invalid="ignore", divide="ignore"):

        def cont(va, vb, steps):
            v = va + (va - vb) * steps
            return np.where(v > 0, 1.0 / v, np.inf)

        def spread(slope, factor):
            return sigmas * np.sqrt(sigma2 + (np.nan_to_num(slope) * blur) ** 2) * factor

        three = np.abs(cont(V[a1], V[a2], 1.0) - ra) <= spread(np.abs(R[a1] - R[a2]), f1)
        anchored = three | (np.abs(R[a1] - ra) <= spread0)
        dev = np.abs(cont(V[a], V[a1], float(i)) - r)
        sp = spread(np.abs(ra - R[a1]), fi)
        if fit3:
            c3 = np.flatnonzero(
                three & (np.abs(ra - R[a2]) <= flat_tol) & (np.abs(ra - r) > margin)
            )
            v3 = (V[a][c3] + V[a1][c3] + V[a2][c3]) / 3.0 - (V[a2][c3] - V[a][c3]) / 2.0 * (i + 1)
            dev[c3] = np.abs(np.where(v3 > 0, 1.0 / v3, np.inf) - r[c3])
            sp[c3] *= c3scale
        tan_a = r * np.abs(V[a] - V[a1]) / step
        tan_x = r * C[a] / (ra * ra) / step_x
        cos_inc = 1.0 / np.sqrt(1.0 + tan_a * tan_a + tan_x * tan_x)
        ok = anchored & (dev > sp) & (dev * cos_inc > across)
        gap = np.fmin(np.abs(ra - r), dev)
        near = ok & (ra < r - margin) & (gap < max_gap)
        front = r - ra * (1.0 + step) > margin
        hidden = ok & (ra < r - margin) & ~(gap < max_gap)
        end = ok & (ra < r + max_gap) & (gap < max_gap)
        off_end |= end
        c = np.flatnonzero(end & ~met)
        met |= anchored & (ra < r + max_gap)
        g = V[a][c] - V[a1][c]
        v_c = V[a][c] + g * i
        pulled = np.abs(1.0 / (v_c - g * half) - 1.0 / v_c)
        off_blend[c[dev[c] > sp[c] + pulled]] = True
        far = ok & (ra > r + margin) & (gap < max_gap)
    return anchored, ok, near, far, front, hidden


@pytest.mark.parametrize("fit3", [False, True])
def test_anchor_pass_matches_numpy(fit3: bool) -> None:
    """One compiled pass gives the anchors, their tests and the updated flags of the
    numpy passes it replaced, to the bit, on ranges with missing beams, flat and
    receding surfaces and blends."""
    rng = np.random.default_rng(3)
    n = 20_000
    r = _ranges(rng, n)
    base = rng.uniform(2.0, 40.0, n)
    # beams 1..6 on a surface through p's neighbourhood (noisy), some far, some missing
    R = {0: r}
    for o in range(1, 7):
        on = base * (1.0 + 0.002 * o * rng.normal(1.0, 0.3, n)) + rng.normal(0.0, 0.005, n)
        R[o] = np.where(rng.random(n) < 0.3, _ranges(rng, n), on)
        R[o][::31] = R[o - 1][::31] if o > 1 else R[o][::31]  # flat: no change per beam
    V = {o: 1.0 / v for o, v in R.items()}
    V[2][::29] = -1e-3  # a surface continued past the horizon
    C = {o: np.abs(rng.normal(0.0, 0.05, n)) for o in R}
    blur = rng.uniform(0.0, 0.4, n)
    sigma, sigmas, margin = 0.004, 4.0, 0.02
    for i in (1, 2, 4):
        k = (
            sigma**2,
            sigmas,
            sigmas * sigma * np.sqrt(2.0),
            float(np.sqrt(6.0)),
            float(np.sqrt((1 + i) ** 2 + i**2 + 1)),
            fit3,
            sigmas * sigma * np.sqrt(2.0),
            0.8 * float(np.sqrt((4.0 / 3.0 + (i + 1) ** 2 / 2.0) / ((1 + i) ** 2 + i**2 + 1))),
            margin,
            np.radians(0.05),
            np.radians(0.07),
            0.03,
            2.5,
            1.0,
        )
        flags = [rng.random(n) < 0.2 for _ in range(3)]
        first = [f.copy() for f in flags]
        mine = [f.copy() for f in flags]
        want = _anchor_numpy(r, R, V, C, blur, i, k, *flags)
        got = anchor_pass(
            r, R[i], R[i + 1], R[i + 2], V[i], V[i + 1], V[i + 2], C[i], blur, i, *k, *mine
        )
        for w, g in zip(want, got, strict=True):
            assert w.any() and not w.all()  # every test decides somewhere
            assert np.array_equal(w, g)
        for w, g, f in zip(flags, mine, first, strict=True):
            assert np.array_equal(w, g) and not np.array_equal(w, f)  # updated alike


def test_spread_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    n = 5000
    ra, rb = _ranges(rng, n), _ranges(rng, n)
    blur = rng.uniform(0.0, 0.4, n)
    sigma, sigmas = 0.004, 4.0
    for i in (0, 1, 3):
        factor = np.sqrt((1 + i) ** 2 + i**2 + 1)
        slope = np.abs(ra - rb)
        old = sigmas * np.sqrt(sigma**2 + (np.nan_to_num(slope) * blur) ** 2) * factor
        assert np.array_equal(spread_of(slope, blur, sigma**2, sigmas, factor), old)


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


def test_behind_both_matches_numpy() -> None:
    """The returns with both beams behind them by more than the margin and less than
    max_gap, as the numpy expression picked them (missing beams: NaN)."""
    rng = np.random.default_rng(11)
    n = 20_000
    r = _ranges(rng, n)
    r0 = r + rng.uniform(-1.0, 4.0, n)
    r1 = r + rng.uniform(-1.0, 4.0, n)
    r0[::37] = np.nan
    margin, max_gap = 0.05, 2.5
    with np.errstate(invalid="ignore"):
        d0, d1 = r0 - r, r1 - r
        want = np.flatnonzero((d0 > margin) & (d1 > margin) & (d0 < max_gap) & (d1 < max_gap))
    got = behind_both(r, r0, r1, margin, max_gap)
    assert 0 < want.size < n // 2
    assert got.dtype == np.int64 and np.array_equal(got, want)
