"""The quadrant test of ``roughedge.py``: shrub returns over a slope go, crests stay."""

from __future__ import annotations

import numpy as np

from terrasift.synthetic import rural
from terrasift.workers.ground.nist import NistParams, classify_ground
from terrasift.workers.ground.roughedge import edge_high


def _slope_with_shrubs(density: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 25 % slope 80 m square with 3 cm noise and a ridge 1 m high along y = 40 (a
    crest, ground), and 30 shrubs (radius 1.5 m) whose returns stand 0.3–0.6 m over it."""
    rng = np.random.default_rng(seed)
    n = int(80 * 80 * density)
    xy = rng.uniform(0, 80, (n, 2))
    ridge = 1.0 * np.exp(-(((xy[:, 1] - 40) / 3.0) ** 2))
    z = 0.25 * xy[:, 0] + ridge + rng.normal(0, 0.03, n)
    centres = rng.uniform(5, 75, (30, 2))
    shrub = np.zeros(n, dtype=bool)
    for c in centres:
        inside = np.hypot(*(xy - c).T) < 1.5
        pick = inside & (rng.random(n) < 0.5)  # half the pulses reach the ground
        z[pick] += rng.uniform(0.3, 0.6, np.count_nonzero(pick))
        shrub |= pick
    crest = (np.abs(xy[:, 1] - 40) < 1.0) & ~shrub
    return np.column_stack([xy, z]), shrub, crest


def test_shrub_returns_over_a_slope_go_and_the_ground_and_a_crest_stay() -> None:
    xyz, shrub, crest = _slope_with_shrubs(1.0)
    high = edge_high(xyz, np.ones(xyz.shape[0], dtype=bool))
    assert np.count_nonzero(high & shrub) >= 0.3 * np.count_nonzero(shrub)
    assert not (high & ~shrub).any()
    assert not (high & crest).any()


def test_ground_sparser_than_the_density_gate_is_left_alone() -> None:
    # The ground holds about 1 point per m²: a gate above that stops the test.
    xyz, _, _ = _slope_with_shrubs(1.0)
    ground = np.ones(xyz.shape[0], dtype=bool)
    assert edge_high(xyz, ground).any()
    assert not edge_high(xyz, ground, density=2.5).any()


def test_the_stage_takes_shrub_returns_the_roughness_tests_leave_on_a_rural_slope() -> None:
    # Rural seed 5: a 15-40 % slope at 0.74 pts/m², all single returns; the close fit
    # leaves shrub returns 0.3-0.6 m high that stand over the ground around them.
    sc = rural.FAMILIES["rural_slope"](5)
    before = classify_ground(sc.xyz, NistParams(rough_edge=0))
    after = classify_ground(sc.xyz, NistParams())
    taken = before & ~after
    assert not (after & ~before).any()
    assert np.count_nonzero(taken & ~sc.is_ground) >= 5
    assert np.count_nonzero(taken & sc.is_ground) <= 1
