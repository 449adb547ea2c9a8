"""The compiled fast paths of categories and filters give what their simple reference
implementations give."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_features import DITCHLIKE

from terrasift.workers.categories import NODATA
from terrasift.workers.features import (
    builtin_filter_names,
    categories_for,
    grid_key,
    load_filter,
    parse_filter,
)
from terrasift.workers.features.search import search_filter, search_rows


def _random_segment(rng: np.random.Generator, base):
    subs = []
    for _ in range(int(rng.integers(1, 6))):
        u = base.subsegments[int(rng.integers(0, len(base.subsegments)))]
        lo = int(rng.integers(0, 4))
        hi = lo + int(rng.integers(0, 3 if rng.random() < 0.6 else 14))
        subs.append(
            replace(
                u,
                min_len=lo,
                max_len=hi,
                max_errors=int(rng.integers(0, 3)),
                exclude=bool(rng.random() < 0.3),
            )
        )
    top = sum(u.max_len for u in subs)
    seg = replace(base, subsegments=tuple(subs))
    if rng.random() < 0.5:
        seg = replace(seg, min_total=int(rng.integers(0, 4)), max_total=min(63, top))
    if top > 63:
        seg = replace(seg, max_total=63)
    return seg


def test_compiled_row_search_equals_the_array_passes():
    """Random segments (empty runs, misses allowed, excluded runs, matches over 32 and 63
    tiles) on random rows with nodata: the compiled search marks the tiles the array
    passes mark."""
    rng = np.random.default_rng(22)
    base = parse_filter(DITCHLIKE).segments[0]
    searched = 0
    for trial in range(150):
        p = [0.4, 0.25, 0.25, 0.1] if trial % 2 else [0.8, 0.08, 0.08, 0.04]
        inc = rng.choice(np.array([0, 1, 5, NODATA], np.uint8), size=(23, 70), p=p)
        arrays = (inc, np.zeros_like(inc), np.zeros_like(inc))
        seg = _random_segment(rng, base)
        want = search_rows(arrays, seg, band=9, compiled=False)
        got = search_rows(arrays, seg, band=9)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert (got == want).all(), (trial, seg)
        searched += int(want.any())
    assert searched > 50  # most segments mark something


@pytest.mark.parametrize("name", builtin_filter_names())
def test_compiled_search_equals_the_array_passes_for_the_builtin_filters(name):
    rng = np.random.default_rng(4)
    z = np.cumsum(rng.normal(0, 0.08, (120, 90)), axis=1)  # a rough surface, 0.5 m cells
    z += np.cumsum(rng.normal(0, 0.05, (120, 90)), axis=0)
    flt = load_filter(name)
    cats, stepped = categories_for(z, 0.5, [flt])
    key = grid_key(flt)
    on = cats if key is None else stepped[key]
    h, v = search_filter(on, flt)
    hr, vr = search_filter(on, flt, compiled=False)
    assert (h == hr).all() and (v == vr).all()


@pytest.mark.parametrize(
    ("shape", "size"), [((60, 45), 12), ((31, 52), 7), ((9, 4), 6), ((1, 1), 4), ((17, 13), 1)]
)
def test_compiled_median_equals_scipy(shape, size):
    """The regional slope's median filter gives scipy's ``median_filter`` (edges taken
    as the nearest cell) on rough and smooth fields, with ties (level tiles) and with
    windows wider than the field."""
    from scipy import ndimage

    from terrasift.workers._median_kernels import median_filter

    rng = np.random.default_rng(sum(shape) + size)
    rough = rng.normal(size=shape)
    smooth = ndimage.gaussian_filter(rng.normal(size=shape), 3)
    for a in (rough, smooth):
        a = a.copy()
        a[rng.random(shape) < 0.2] = 0.0
        a[rng.random(shape) < 0.1] = 0.125
        want = ndimage.median_filter(a, size=size, mode="nearest")
        assert np.array_equal(median_filter(a, size), want)


@pytest.mark.parametrize("d", [1, 3, 5, 9, 21])
def test_square_dilation_equals_scipy(d):
    """The rings around objects grow as scipy's dilation by a d × d square does, up to
    the array's edges, on sparse and dense masks and on a single row."""
    from scipy import ndimage

    from terrasift.workers.features.objects import square_dilation

    rng = np.random.default_rng(d)
    for shape, p in (((37, 23), 0.02), ((37, 23), 0.3), ((1, 40), 0.1), ((5, 5), 0.5)):
        mask = rng.random(shape) < p
        want = ndimage.binary_dilation(mask, np.ones((d, d), bool))
        got = square_dilation(mask, d)
        assert got.dtype == bool and np.array_equal(got, want)
