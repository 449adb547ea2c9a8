"""Returns confirmed on a surface another scan position sees (mixed_cross)."""

from __future__ import annotations

import numpy as np

from terrasift.synthetic.scan import make_scan_tile
from terrasift.workers.mixed import MixedParams, mark_mixed
from terrasift.workers.mixed_cross import PositionGrid, cross_check

STEP = np.radians(0.4)


def _wall_scan(origin, x_wall, rng, az0=-0.3, sigma=0.003):
    """Returns of a sensor at ``origin`` on the wall x = x_wall, on its 0.4° grid."""
    az = np.arange(az0, 0.3, STEP)
    el = np.arange(-0.05, 0.15, STEP)
    A, E = (g.ravel() for g in np.meshgrid(az, el, indexing="ij"))
    u = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=1)
    t = (x_wall - origin[0]) / u[:, 0]
    t = t + rng.normal(0.0, sigma, t.size)
    return origin + u * t[:, None]


def test_a_return_on_a_surface_another_position_sees_is_confirmed():
    rng = np.random.default_rng(3)
    oa, ob = np.array([0.0, 0.0, 1.5]), np.array([0.0, 4.0, 2.0])
    a = _wall_scan(oa, 12.0, rng)
    b = _wall_scan(ob, 12.0, rng, az0=-0.7)
    # A's returns: on the wall, and 10 cm in front of it on their own rays (a blend)
    ra = a - oa
    front = oa + ra * (1.0 - 0.10 / np.linalg.norm(ra, axis=1))[:, None]
    xyz = np.vstack([a, front, b])
    ids = np.r_[np.zeros(2 * len(a), int), np.ones(len(b), int)]
    marked = np.r_[np.ones(2 * len(a), bool), np.zeros(len(b), bool)]
    grids = [PositionGrid(STEP, STEP, 0.003), PositionGrid(STEP, STEP, 0.003)]
    got = cross_check(xyz, ids, np.vstack([oa, ob]), grids, marked)[0]
    on, off = got[: len(a)], got[len(a) : 2 * len(a)]
    assert on.mean() > 0.6  # within 2 sd, where B (higher) sees the wall
    assert not off.any()  # a return off the wall is never confirmed
    assert not got[2 * len(a) :].any()  # unmarked returns are not looked at
    # B's own returns marked mixed are no witness
    marked_b = marked.copy()
    marked_b[2 * len(a) :] = True
    assert not cross_check(xyz, ids, np.vstack([oa, ob]), grids, marked_b)[0][: len(a)].any()


def test_cross_positions_takes_off_false_marks_on_a_shared_scene():
    tile = make_scan_tile(
        [(0.0, -4.0, 1.5), (1.0, 4.0, 2.2)],
        seed=2,
        shared=True,
        step_deg=0.4,
        footprint_steps=1.3,
        sub_rays=(9, 5),
        azimuth_deg=(-25.0, 25.0),
        elevation_deg=(-25.0, 12.0),
        n_boards=3,
        n_poles=2,
        object_range=(5.0, 12.0),
        las_scale=0.001,
    )
    args = (tile.xyz,)
    plain = mark_mixed(*args, MixedParams(), tile.origins, tile.scan_id).marked
    cross = mark_mixed(*args, MixedParams(cross_positions=True), tile.origins, tile.scan_id).marked
    truth = tile.is_mixed
    assert not (cross & ~plain).any()  # the check only ever takes marks off
    fp0, fp1 = np.count_nonzero(plain & ~truth), np.count_nonzero(cross & ~truth)
    tp0, tp1 = np.count_nonzero(plain & truth), np.count_nonzero(cross & truth)
    assert fp1 < fp0  # fewer false marks
    assert tp0 - tp1 < 0.25 * (fp0 - fp1)  # far fewer true marks lost than false ones


def test_a_blend_in_another_positions_free_space_is_marked():
    rng = np.random.default_rng(4)
    oa, ob = np.array([0.0, 0.0, 1.5]), np.array([3.0, 3.0, 2.0])
    a = _wall_scan(oa, 12.0, rng)
    b = _wall_scan(ob, 12.0, rng, az0=-0.7)
    ra = a - oa
    az = np.arctan2(ra[:, 1], ra[:, 0])
    col = np.abs(az - az[len(az) // 2]) < 1e-9  # one column of A's beams
    # that column blends the wall with something 60 cm in front of it: off A's wall
    # along its rows, in the space B looks through to the wall
    a[col] = oa + ra[col] * (1.0 - 0.6 / np.linalg.norm(ra[col], axis=1))[:, None]
    xyz = np.vstack([a, b])
    ids = np.r_[np.zeros(len(a), int), np.ones(len(b), int)]
    marked = np.zeros(len(xyz), bool)
    grids = [PositionGrid(STEP, STEP, 0.003), PositionGrid(STEP, STEP, 0.003)]
    _, free = cross_check(xyz, ids, np.vstack([oa, ob]), grids, marked, free_margin=0.3)
    assert free[: len(a)][col].mean() > 0.6  # B's beams pass the blends to the wall
    assert not free[: len(a)][~col].any()  # A's wall returns lie on a smooth surface
    assert not cross_check(xyz, ids, np.vstack([oa, ob]), grids, marked)[1].any()  # off
