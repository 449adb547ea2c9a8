"""ground.ptd against exact synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.errors import ParameterError
from terrasift.metrics import ground_score
from terrasift.synthetic.terrain import Surface, make_scene
from terrasift.workers.ground.ptd import PtdParams, classify_ground
from terrasift.workers.registry import _STAGES


@pytest.fixture(scope="module")
def scene():
    return make_scene(size=90, density=4, n_buildings=2, building_size=(8.0, 10.0), seed=7)


def test_registered_with_table1_presets():
    stage = _STAGES["ground.ptd"]
    assert stage.run is classify_ground and stage.params is PtdParams
    c = PtdParams.preset("conservative")
    a = PtdParams.preset("aggressive")
    assert (c.terrain_angle, c.iteration_angle, c.iteration_distance, c.max_building_size) == (
        75,
        15,
        1.0,
        10,
    )
    assert (a.terrain_angle, a.iteration_angle, a.iteration_distance, a.max_building_size) == (
        88,
        20,
        1.2,
        10,
    )
    with pytest.raises(ParameterError):
        PtdParams.preset("default", iteration_angle=-1)


def test_scene_accuracy(scene):
    pred = classify_ground(scene.xyz, PtdParams())
    score = ground_score(scene.is_ground, pred)
    assert score.type1 < 0.03, score
    assert score.kappa > 0.85, score
    # Vegetation under 0.5 m is ground-like at 3 cm noise; above it must stay object.
    above = np.isin(scene.truth, (4, 5, 6))
    assert np.count_nonzero(pred & above) < 0.05 * np.count_nonzero(above)
    # Nothing from roofs or tree tops, and no low or high outlier, is ground.
    assert not pred[scene.truth == 6].any()
    assert np.count_nonzero(pred[scene.truth == 5]) <= 0.01 * np.count_nonzero(scene.truth == 5)


def test_low_outliers_do_not_seed(scene):
    # Deep outliers (20 m under the terrain) would be the lowest point of their
    # cells; they must be dropped and the ground around them still found.
    rng = np.random.default_rng(1)
    x0, y0, x1, y1 = scene.bounds
    k = 12
    ox, oy = rng.uniform(x0 + 5, x1 - 5, k), rng.uniform(y0 + 5, y1 - 5, k)
    xyz = np.vstack([scene.xyz, np.column_stack([ox, oy, scene.surface(ox, oy) - 20.0])])
    truth = np.r_[scene.is_ground, np.zeros(k, bool)]
    pred = classify_ground(xyz, PtdParams())
    assert not pred[-k:].any()
    base = ground_score(scene.is_ground, classify_ground(scene.xyz, PtdParams()))
    assert ground_score(truth, pred).type1 < base.type1 + 0.02


def test_shallow_returns_under_the_terrain_do_not_drag_the_tin_down():
    # Returns 0.5-1.5 m under the ground pass the distance test; in the TIN each
    # would tilt its facets down and the true ground around it would fail.
    s = make_scene(
        size=120, density=8, n_buildings=0, tree_density=0, bush_density=0, outlier_rate=0, seed=4
    )
    rng = np.random.default_rng(3)
    x0, y0, x1, y1 = s.bounds
    k = 60
    ox, oy = rng.uniform(x0 + 5, x1 - 5, k), rng.uniform(y0 + 5, y1 - 5, k)
    xyz = np.vstack(
        [s.xyz, np.column_stack([ox, oy, s.surface(ox, oy) - rng.uniform(0.5, 1.5, k)])]
    )
    truth = np.r_[s.is_ground, np.zeros(k, bool)]
    score = ground_score(truth[:-k], classify_ground(xyz, PtdParams())[:-k])
    assert score.type1 < 0.002, score  # 0.5 % with pit_depth=None
    # a real hollow (a 2 m wide, 0.6 m deep pit sampled densely) stays ground
    hollow = np.hypot(s.xyz[:, 0] - (x0 + 60), s.xyz[:, 1] - (y0 + 60)) < 1.0
    pitted = s.xyz.copy()
    pitted[hollow, 2] -= 0.6
    assert classify_ground(pitted, PtdParams())[hollow].mean() > 0.9


def test_dense_cloud_with_returns_under_the_terrain():
    # At 20 pts/m² the outliers under the terrain neighbour each other in the
    # TIN; as candidates they cost 13 % of the ground (low_candidates=False).
    s = make_scene(100, 20.0, seed=5)
    score = ground_score(s.is_ground, classify_ground(s.xyz, PtdParams()))
    assert score.type1 < 0.005, score
    assert score.kappa > 0.95, score


def test_translation_invariant(scene):
    a = classify_ground(scene.xyz, PtdParams())
    # a shift by whole multiples of the 240 m anchor keeps every seed cell
    b = classify_ground(scene.xyz - np.array([499_920.0, 5_400_000.0, 0.0]), PtdParams())
    assert np.mean(a == b) > 0.999


def test_steep_smooth_slope_is_found():
    # A 35° planar slope (no objects): the filter must climb it, not stop at the seeds.
    s = make_scene(
        size=60,
        density=4,
        surface=Surface(gx=0.7, gy=0.0, waves=()),
        n_buildings=0,
        tree_density=0,
        bush_density=0,
        outlier_rate=0,
        seed=2,
    )
    pred = classify_ground(s.xyz, PtdParams())
    assert pred.mean() > 0.995


def test_tiny_inputs():
    assert classify_ground(np.zeros((0, 3)), PtdParams()).shape == (0,)
    assert not classify_ground(np.array([[0.0, 0, 0], [1, 0, 0]]), PtdParams()).any()
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    assert classify_ground(line, PtdParams()).shape == (10,)


def test_labels_do_not_depend_on_point_order(scene):
    a = classify_ground(scene.xyz, PtdParams())
    perm = np.random.default_rng(5).permutation(len(scene))
    b = classify_ground(scene.xyz[perm], PtdParams())
    assert np.array_equal(a[perm], b)


def test_roofs_wider_than_seed_cells_are_dropped():
    # 26-30 m buildings fill whole 12 m seed cells, whose lowest points are roof:
    # the roofs grow as raised islands of the TIN, and must be dropped.
    s = make_scene(
        size=120,
        density=4,
        n_buildings=3,
        building_size=(26.0, 30.0),
        building_height=(5.0, 12.0),
        tree_density=0,
        bush_density=0,
        outlier_rate=0,
        seed=4,
    )
    roof = s.truth == 6
    off = classify_ground(s.xyz, PtdParams(island_step=None))
    assert off[roof].mean() > 0.1  # the case the island test is for
    on = classify_ground(s.xyz, PtdParams())
    assert on[roof].mean() < 0.01
    assert ground_score(s.is_ground, on).type1 <= ground_score(s.is_ground, off).type1 + 0.005
