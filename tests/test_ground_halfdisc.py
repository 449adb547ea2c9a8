"""Half-disc test of low vegetation beside slope breaks (``halfdisc.py``)."""

from __future__ import annotations

import numpy as np

from terrasift.workers.ground.halfdisc import half_disc_vegetation
from terrasift.workers.ground.roughness import rough_points


def _embankment(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 2 % slope at 0.5 pts/m² with a 2 m raised bench (1:1 side from x = 30 to 32),
    and shrub returns 0.4–0.8 m high on the flats within 1–4 m of the toe and the crest.
    Returns xyz, the shrub mask and the crest mask (ground within 1.5 m of the crest)."""
    rng = np.random.default_rng(seed)
    n = int(0.5 * 80 * 80)
    xy = rng.uniform(0, 80, (n, 2))
    ground_z = 0.02 * xy[:, 1] + np.clip(xy[:, 0] - 30.0, 0.0, 2.0)
    m = 40
    sx = np.concatenate([rng.uniform(26, 29, m // 2), rng.uniform(33, 36, m // 2)])
    sxy = np.column_stack([sx, rng.uniform(5, 75, m)])
    shrub_z = 0.02 * sxy[:, 1] + np.clip(sxy[:, 0] - 30.0, 0.0, 2.0) + rng.uniform(0.4, 0.8, m)
    xyz = np.column_stack(
        [np.vstack([xy, sxy]), np.concatenate([ground_z, shrub_z]) + rng.normal(0, 0.02, n + m)]
    )
    shrub = np.arange(n + m) >= n
    crest = ~shrub & (xyz[:, 0] > 32.0) & (xyz[:, 0] < 33.5)
    return xyz, shrub, crest


def test_shrubs_beside_a_break_are_taken_and_the_crest_kept() -> None:
    xyz, shrub, crest = _embankment()
    everything = np.ones(len(xyz), dtype=bool)
    high = half_disc_vegetation(xyz, everything, k=12, rounds=5, factor=4.0, floor=0.1)
    assert high[shrub].mean() >= 0.8
    assert not high[crest].any()
    assert high[~shrub].mean() < 0.01


def test_the_roughness_test_alone_misses_them() -> None:
    # The deviation of 48 neighbours across the break lifts the roughness threshold.
    xyz, shrub, _ = _embankment()
    everything = np.ones(len(xyz), dtype=bool)
    rough = rough_points(xyz, everything, 48, 5.0, 2.0, 0.05)
    half = half_disc_vegetation(xyz, everything & ~rough, k=12, rounds=5, factor=4.0, floor=0.1)
    assert rough[shrub].mean() < 0.5
    assert (rough | half)[shrub].mean() > rough[shrub].mean() + 0.3


def test_nothing_on_bare_ground_or_too_few_points() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 50, (1500, 2))
    xyz = np.column_stack([xy, 0.3 * xy[:, 0] + rng.normal(0, 0.03, 1500)])
    ground = np.ones(1500, dtype=bool)
    assert half_disc_vegetation(xyz, ground, 12, 5, 4.0, 0.1).mean() < 0.005
    few = np.zeros(1500, dtype=bool)
    few[:10] = True
    assert not half_disc_vegetation(xyz, few, 12, 5, 4.0, 0.1).any()
