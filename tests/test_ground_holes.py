"""Screening on a HoledTin: the same vertices and the same TIN as Tin.without's rounds."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from terrasift.workers.ground import holes
from terrasift.workers.ground.tin import Tin, screen


def _scene(n: int, seed: int, roofs: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Random ground on a gentle hill with flat roofs 3-6 m up (peeled off over
    several rounds, outside in) and a few spikes and pits; per-point slopes."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(n)
    xy = rng.uniform(0, side, (n, 2))
    z = 0.05 * xy[:, 0] + 0.002 * (xy[:, 1] - side / 2) ** 2 + rng.normal(0, 0.03, n)
    for _ in range(roofs):
        c = rng.uniform(0.1 * side, 0.9 * side, 2)
        half = rng.uniform(3, 8, 2)
        on = np.all(np.abs(xy - c) < half, axis=1)
        z[on] += rng.uniform(3, 6)
    odd = rng.choice(n, max(n // 100, 3), replace=False)
    z[odd] += rng.choice([-4.0, 4.0], odd.size)
    slopes = np.column_stack([np.full(n, 0.05), 0.004 * (xy[:, 1] - side / 2)])
    return np.column_stack([xy, z]), slopes


def _same_tin(a: Tin | None, b: Tin | None) -> None:
    assert (a is None) == (b is None)
    if a is None or b is None:
        return
    for name in ("simplices", "neighbors"):
        x, y = np.asarray(getattr(a.tri, name)), np.asarray(getattr(b.tri, name))
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    for x, y in ((a.xy, b.xy), (a.z, b.z), (a._transform(), b._transform())):
        assert x.tobytes() == y.tobytes()


@pytest.mark.parametrize(
    ("n", "seed", "roofs", "with_slopes", "rim_len"),
    [
        (3000, 1, 6, True, 0.0),
        (3000, 2, 6, False, 0.0),
        (5000, 3, 10, True, 4.0),
        (400, 4, 3, True, 0.0),  # small: rims beyond 30 % of the TIN, handed over
        (30, 5, 0, False, 0.0),
    ],
)
def test_holed_rounds_give_tin_without_s_vertices_and_tin(
    monkeypatch, n, seed, roofs, with_slopes, rim_len
):
    xyz, slopes = _scene(n, seed, roofs)
    kw = dict(slopes=slopes if with_slopes else None, rim_len=rim_len, rim_band=2 * rim_len)
    patched = []
    real_patch = holes.HoledTin.patch

    def counting(self, drop):
        got = real_patch(self, drop)
        patched.append(got is not None)
        return got

    monkeypatch.setattr(holes.HoledTin, "patch", counting)
    ids, tin = screen(xyz, 0.5, 1.0, **kw)
    monkeypatch.setattr(holes.HoledTin, "of", classmethod(lambda cls, tin: None))
    ids_ref, tin_ref = screen(xyz, 0.5, 1.0, **kw)
    assert np.array_equal(ids, ids_ref)
    _same_tin(tin, tin_ref)
    if n >= 3000:
        assert sum(patched) >= 3  # rounds done on the holed TIN, not handed over
    else:
        assert False in patched  # handed over to Tin.without
    assert ids.size < n


def test_holed_rounds_stop_at_max_rounds_as_before(monkeypatch):
    xyz, slopes = _scene(3000, 6, 8)
    for rounds in (1, 2, 3):
        ids, tin = screen(xyz, 0.5, 1.0, slopes=slopes, max_rounds=rounds)
        with monkeypatch.context() as m:
            m.setattr(holes.HoledTin, "of", classmethod(lambda cls, tin: None))
            ids_ref, tin_ref = screen(xyz, 0.5, 1.0, slopes=slopes, max_rounds=rounds)
        assert np.array_equal(ids, ids_ref)
        _same_tin(tin, tin_ref)


def test_fans_are_the_mesh_adjacency():
    xyz, _ = _scene(2000, 7, 0)
    tin = Tin(xyz)
    holed = holes.HoledTin.of(tin)
    assert holed is not None
    ptr, idx = tin.neighbours()
    verts = np.arange(tin.n_vertices)
    got = holed.rows(verts)
    assert got is not None
    assert np.array_equal(got[0], ptr) and np.array_equal(got[1], idx)
