"""Isolated low points among the ground: lone returns under the terrain, not hollows."""

from __future__ import annotations

import numpy as np

from terrasift.workers.ground.lowpoints import LowPointParams, isolated_low_points


def _ground(density: float, size: float = 60.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = int(density * size * size)
    xy = rng.uniform(0, size, (n, 2))
    z = (
        0.3 * xy[:, 0] + 0.5 * np.sin(xy[:, 1] / 4.0) + rng.normal(0, 0.05, n)
    )  # a 17° slope, rolling
    return np.column_stack([xy + [5e5, 5.4e6], z + 200.0])


def test_lone_and_paired_returns_under_the_terrain_are_found_a_cluster_is_kept():
    pts = _ground(8.0)
    n = len(pts)
    rng = np.random.default_rng(1)
    lone = rng.choice(n, 20, replace=False)
    # 2.5 m and more: on the 17° slope, terrain 3 m downhill is 0.9 m lower
    pts[lone, 2] -= rng.uniform(2.5, 6.0, 20)
    # a pair 0.5 m apart, 3 m down; a cluster of five, 2 m down (a pit with returns: kept)
    pair = np.array([[5e5 + 30.0, 5.4e6 + 30.0], [5e5 + 30.5, 5.4e6 + 30.0]])
    cluster = np.array(
        [[5e5 + 45.0 + dx, 5.4e6 + 15.0 + dy] for dx in (0, 0.4) for dy in (0, 0.4, 0.8)]
    )[:5]
    surface = lambda xy: 0.3 * (xy[:, 0] - 5e5) + 0.5 * np.sin((xy[:, 1] - 5.4e6) / 4.0) + 200.0  # noqa: E731
    extra = np.vstack(
        [
            np.column_stack([pair, surface(pair) - 3.0]),
            np.column_stack([cluster, surface(cluster) - 2.0]),
        ]
    )
    xyz = np.vstack([pts, extra])
    ground = np.ones(len(xyz), dtype=bool)
    low = isolated_low_points(xyz, ground, LowPointParams())
    assert low[lone].all()
    assert low[n : n + 2].all()
    assert not low[n + 2 :].any()
    assert not low[np.setdiff1d(np.arange(n), lone)].any()
    # only ground points are judged, and support=0 turns the test off
    assert not isolated_low_points(xyz, ~ground, LowPointParams()).any()
    assert not isolated_low_points(xyz, ground, LowPointParams(support=0)).any()


def test_a_ditch_and_sparse_slopes_are_terrain():
    pts = _ground(8.0, seed=2)
    ditch = np.abs(pts[:, 0] - 5e5 - 30.0) < 0.7  # 1.4 m wide, 1.5 m deep
    pts[ditch, 2] -= 1.5
    assert not isolated_low_points(pts, np.ones(len(pts), bool), LowPointParams()).any()
    # a sparse slope (0.3 points per m²) has no isolated points; at 0.1 per m²
    # there are too few neighbours to judge, so even sunk points stay
    sparse = _ground(0.3, seed=3)
    assert not isolated_low_points(sparse, np.ones(len(sparse), bool), LowPointParams()).any()
    sparser = _ground(0.1, seed=4)
    sparser[::20, 2] -= 3.0
    assert not isolated_low_points(sparser, np.ones(len(sparser), bool), LowPointParams()).any()


def test_lone_returns_in_a_gap_of_dense_data_are_judged_across_it():
    pts = _ground(2.0, size=80.0, seed=5)
    # a strip 20 m wide without data (no overlap between flight lines)
    pts = pts[np.abs(pts[:, 1] - 5.4e6 - 40.0) > 10.0]
    n = len(pts)
    surface = lambda xy: 0.3 * (xy[:, 0] - 5e5) + 0.5 * np.sin((xy[:, 1] - 5.4e6) / 4.0) + 200.0  # noqa: E731
    xy = np.array([[5e5 + x, 5.4e6 + 40.0 + dy] for x, dy in ((15, -3), (35, 2), (55, 0), (70, 4))])
    sunk = np.column_stack([xy, surface(xy) - np.array([1.5, 2.5, 4.0, 6.0])])
    level = np.column_stack([xy + [5.0, 0.0], surface(xy + [5.0, 0.0]) + 0.2])
    xyz = np.vstack([pts, sunk, level])
    ground = np.ones(len(xyz), dtype=bool)
    low = isolated_low_points(xyz, ground, LowPointParams())
    assert low[n : n + 4].all()  # under the terrain across the gap
    assert not low[n + 4 :].any()  # at the terrain's height: kept
    assert not low[:n].any()
    # without the rule they are too alone to be judged
    assert not isolated_low_points(xyz, ground, LowPointParams(lone=0))[n:].any()
