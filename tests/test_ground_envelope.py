"""Lower-envelope ground plane and the isolated-shrub test (ground/envelope.py, roughness.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from terrasift.workers.ground.envelope import envelope_plane, surrounded
from terrasift.workers.ground.lowveg import local_plane
from terrasift.workers.ground.roughness import rough_points


def _neighbourhoods(share: float, seed: int = 0, m: int = 200, k: int = 48):
    """``m`` centres on a 30 % slope (3 cm noise), each with ``k`` neighbours within
    6 m; dense scrub (``share`` of the returns, 0.15-1.2 m above the ground) covers the
    part of the neighbourhood beyond 3 m to the west of the centre."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-6, 6, (m, k, 2))
    z = 0.3 * xy[..., 1] + rng.normal(0, 0.03, (m, k))
    scrub = (rng.random((m, k)) < share) & (xy[..., 0] > -3.0)
    z = z + np.where(scrub, rng.uniform(0.15, 1.2, (m, k)), 0.0)
    near = np.concatenate([xy, z[..., None]], axis=-1)
    centre = np.zeros((m, 3))
    return centre, near


def test_the_envelope_plane_stays_on_the_ground_under_scrub_the_clipped_plane_does_not():
    centre, near = _neighbourhoods(share=0.7)
    lifted, _, _ = local_plane(centre, near, 2.0)
    env, dev, _, _ = envelope_plane(centre, near, 2.0, 0.025)
    # Heights of the centre (on the ground) above each plane: the clipped plane stands
    # decimetres above the ground, the envelope plane within the noise.
    assert np.median(-lifted) > 0.1, np.median(-lifted)
    assert np.abs(np.median(env)) < 0.02, np.median(env)
    assert np.percentile(np.abs(env), 90) < 0.08
    assert np.median(dev) < 0.05


def test_on_bare_ground_the_envelope_plane_is_the_least_squares_plane():
    centre, near = _neighbourhoods(share=0.0, seed=1)
    env, _, _, _ = envelope_plane(centre, near, 2.0, 0.025)
    ls, _, _ = local_plane(centre, near, 1e9, rounds=1)
    assert np.percentile(np.abs(env - ls), 95) < 0.02


def _dike_with_shrubs(seed: int):
    """0.5 pts/m² on a 30 % slope, a dike 2 m high (crest 4 m, sides 1:1.5) across it,
    shrubs whose returns stand 0.3-0.8 m above the ground, three of them just beyond the
    dike's foot (where its neighbours' plane spans the break and the deviation threshold
    is widest)."""
    rng = np.random.default_rng(seed)
    n = 5000
    xy = rng.uniform(0, 100, (n, 2))
    d = np.abs(xy[:, 1] - 50.0)
    dike = 2.0 * np.clip((2.0 + 3.0 - d) / 3.0, 0.0, 1.0)
    z = 0.3 * xy[:, 0] + dike + rng.normal(0, 0.03, n)
    centres = np.vstack([rng.uniform(10, 90, (8, 2)), [[25, 57.0], [50, 43.0], [75, 57.0]]])
    near = cKDTree(centres).query(xy)[0] < 1.5
    shrub = near & (rng.random(n) < 0.7)
    z[shrub] += rng.uniform(0.3, 0.8, np.count_nonzero(shrub))
    return np.column_stack([xy, z]), shrub, d


def test_the_shrub_test_takes_shrubs_beside_a_dike_crest_and_leaves_the_crest():
    xyz, shrub, d = _dike_with_shrubs(4)
    n = xyz.shape[0]
    args = {"k": 48, "factor": 5.0, "clip": 2.0, "floor": 0.05}
    side = shrub & (d > 5.0) & (d < 9.0)  # beyond the dike's foot
    before = rough_points(xyz, np.ones(n, dtype=bool), **args)
    after = rough_points(xyz, np.ones(n, dtype=bool), shrub=0.2, sectors=4, nearest=2, **args)
    assert side.sum() >= 5
    # The deviation test alone leaves shrub returns by the break; the shrub test takes them.
    assert after[side].sum() > before[side].sum()
    assert not (before & ~after).any()
    assert after[shrub].mean() > 0.85
    crest = (d < 2.0) & ~shrub
    edge = (d >= 1.5) & (d <= 5.5) & ~shrub  # crest edge and upper side: convex break
    assert after[crest].mean() < 0.02, after[crest].mean()
    assert after[edge].mean() < 0.01, after[edge].mean()
    assert after[~shrub].mean() < 0.002


def test_a_crest_point_is_not_surrounded_a_shrub_return_is():
    # A level crest 4 m wide (x along it) between sides falling 1:1.5; one shrub
    # return 0.6 m above a slope, ground all round.
    rng = np.random.default_rng(2)
    k = 24
    xy = rng.uniform(-5, 5, (2, k, 2))
    crest = np.where(np.abs(xy[0, :, 1]) < 2, 0.0, -(np.abs(xy[0, :, 1]) - 2) / 1.5)
    slope = 0.2 * xy[1, :, 0]
    near = np.concatenate([xy, np.stack([crest, slope])[..., None]], axis=-1)
    order = np.argsort(np.hypot(near[..., 0], near[..., 1]), axis=1)
    near = np.take_along_axis(near, order[..., None], axis=1)
    centre = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.6]])
    h, _, res, d = envelope_plane(centre, near, 2.0, 0.025)
    assert h[0] > 0.2  # the crest stands above the envelope of its sides…
    ring = surrounded(h, res, d, sectors=4, nearest=3)
    assert not ring[0] and ring[1]  # …but along the crest its neighbours are as high
