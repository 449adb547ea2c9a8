"""Low single returns over the ground fitted close around each point (``closefit.py``)."""

from __future__ import annotations

import numpy as np
from test_ground_halfdisc import _waves

from terrasift.workers.ground.closefit import close_fit_high
from terrasift.workers.ground.halfdisc import half_disc_vegetation


def test_the_close_fit_takes_low_shrubs_the_half_disc_test_leaves() -> None:
    # 0.3 pts/m², waves 0.2 m high, single shrub returns 0.3-0.5 m: the half-disc test
    # with its close quadratic leaves 20-25 of the 60 (measured); the close fit takes
    # 14-16 of those, 0-2 of 3000 ground points (measured on these draws).
    for seed in range(3):
        xyz, shrub = _waves(seed)
        left = ~half_disc_vegetation(xyz, np.ones(len(xyz), bool), 12, 5, 4.0, 0.1, 30, 5.0, 12)
        high = close_fit_high(xyz, left)
        assert not high[~left].any()
        assert high[shrub & left].mean() > 0.5
        assert high[~shrub].mean() < 0.001


def test_a_mound_and_a_bank_are_ground() -> None:
    # Ground that bends within metres, sampled at 0.3 pts/m² without vegetation: a mound
    # 0.6 m high (sigma 2 m) and a field bank rising 0.8 m over 3 m stay ground (4 points
    # go on this draw without the tests beside the height: deviation around, nearest
    # points, wider quadratic, ceiling).
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 100, (3000, 2))
    r2 = (xy[:, 0] - 30) ** 2 + (xy[:, 1] - 50) ** 2
    z = 0.03 * xy[:, 1] + 0.6 * np.exp(-r2 / 8.0) + 0.8 * np.clip((xy[:, 0] - 70) / 3, 0, 1)
    xyz = np.column_stack([xy, z + rng.normal(0, 0.02, 3000)])
    assert not close_fit_high(xyz, np.ones(3000, bool)).any()


def test_fits_taken_from_the_last_round_are_the_fits_made_afresh():
    from scipy.spatial import cKDTree

    from terrasift.workers.ground.closefit import _quad_heights

    rng = np.random.default_rng(5)
    n = 3000
    xy = rng.uniform(0, 60, (n, 2))
    z = 0.1 * xy[:, 0] + 0.01 * (xy[:, 1] - 30) ** 2 / 10 + rng.normal(0, 0.03, n)
    z[rng.random(n) < 0.1] += rng.uniform(0.2, 0.6)
    xyz = np.column_stack([xy, z])
    g = np.arange(n)

    def heights(sure, last=None):
        s = np.flatnonzero(sure)
        pos = np.full(n, -1)
        pos[s] = np.arange(s.size)
        return _quad_heights(xyz, g, s, cKDTree(xyz[s, :2]), pos, 12, 0.15, last)

    first = heights(np.ones(n, dtype=bool))
    sure = first[0] <= 0.15  # the next round's sure points: some neighbours gone
    fresh, reused = heights(sure), heights(sure, first)
    same = np.all(fresh[2] == first[2], axis=1)
    assert 0.2 < same.mean() < 0.99  # both kinds of rows
    assert fresh[0].tobytes() == reused[0].tobytes()
    assert fresh[1].tobytes() == reused[1].tobytes()
    assert np.array_equal(fresh[2], reused[2])
