"""Steepness test, rotated classification and the cliff scenes."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.synthetic.cliffs import make_cliffs
from terrasift.workers.ground.ptd import PtdParams, classify_ground
from terrasift.workers.ground.rotation import (
    RotationParams,
    SteepParams,
    classify_rotated,
    rotation_matrix,
    steepness,
)


@pytest.fixture(scope="module")
def cliffs():
    return make_cliffs(length=24, density=5, seed=11)


def _plane(step: float) -> np.ndarray:
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 150, (20000, 2))
    z = 0.02 * xy[:, 0] + np.where(xy[:, 0] > 75, step, 0.0)
    return np.column_stack([xy + [5e5, 5.4e6], z])


def test_rotation_matrix_tips_faces_up():
    for k in range(8):
        az = 45.0 * k
        r = rotation_matrix(az, 30.0)
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
        facing = np.array([np.sin(np.radians(az)), np.cos(np.radians(az)), 0.0])
        assert np.isclose((r @ facing)[2], 0.5)  # a vertical face now looks 30° up
        assert np.isclose((r @ [0, 0, 1.0])[2], np.cos(np.radians(30)))


def test_steepness_flat_vs_cliff():
    flat = steepness(_plane(0.0), SteepParams())
    cliff = steepness(_plane(25.0), SteepParams())
    assert not flat.steep and flat.facet_share == 0.0 and flat.n_facets > 50
    # One straight 25 m step across a 150 m block: few facets, but only steep ones there.
    assert cliff.facet_share > 0.003 and cliff.steep == (cliff.facet_share > 0.01)
    assert steepness(_plane(25.0), SteepParams(steep_share=0.002)).steep
    assert not steepness(_plane(25.0), SteepParams(steep_share=0.5)).steep
    assert not steepness(_plane(25.0), SteepParams(min_rise=30.0)).steep


def test_classify_rotated_is_or_about_centroid():
    pts = _plane(0.0)[:500]
    seen = []

    def fake_ground(p):
        seen.append(p.copy())
        return p[:, 2] < np.median(p[:, 2])

    res = classify_rotated(
        pts,
        fake_ground,
        RotationParams(directions=4, angle=20, edge_margin=0.0, context=None, face_evidence=False),
    )
    assert len(seen) == 5
    base = seen[0][:, 2] < np.median(seen[0][:, 2])
    expect = base.copy()
    for p in seen[1:]:
        assert np.allclose(p.mean(axis=0), pts.mean(axis=0))  # turned about the centroid
        assert np.allclose(np.linalg.norm(p - p[0], axis=1), np.linalg.norm(pts - pts[0], axis=1))
        lab = p[:, 2] < np.median(p[:, 2])
        expect |= lab
    assert np.array_equal(res.is_ground, expect)
    assert res.added == [
        int(np.count_nonzero((p[:, 2] < np.median(p[:, 2])) & ~base)) for p in seen[1:]
    ]
    # With an edge margin, rotated runs only add points inside the margin.
    trimmed = classify_rotated(
        pts,
        fake_ground,
        RotationParams(directions=4, angle=20, edge_margin=20.0, context=None, face_evidence=False),
    )
    assert np.all(trimmed.is_ground <= res.is_ground) and sum(trimmed.added) < sum(res.added)
    # A given unrotated labelling is used instead of running it again.
    seen.clear()
    res2 = classify_rotated(
        pts, fake_ground, RotationParams(directions=4, angle=20), unrotated=np.zeros(500, bool)
    )
    assert len(seen) == 4 and res2.unrotated == 0


def test_cliff_truth_is_exact(cliffs):
    g = cliffs.is_ground
    steep = cliffs.extra["steep"]
    covered = cliffs.extra["covered"]
    assert steep.sum() > 300 and covered.sum() > 100
    assert np.all(cliffs.extra["face_angle"][steep] > 60)
    # Every covered ground point has ground above it at (nearly) the same x, y.
    from scipy.spatial import cKDTree

    tree = cKDTree(cliffs.xyz[g & ~covered, :2])
    zg = cliffs.xyz[g & ~covered, 2]
    idx = tree.query_ball_point(cliffs.xyz[covered, :2][:50], 1.0)
    for z, near in zip(cliffs.xyz[covered, 2][:50], idx, strict=True):
        assert near and zg[near].max() > z + 1.0
    # The 2.5-D surface is the lowest ground: no ground point lies below it.
    from terrasift.synthetic.cliffs import PROFILE

    corner = (
        np.min(np.abs(cliffs.extra["u"][:, None] - np.array(PROFILE)[None, :, 0]), axis=1) < 0.2
    )
    flatish = g & ~steep & ~corner
    zs = cliffs.surface(cliffs.xyz[flatish, 0], cliffs.xyz[flatish, 1])
    assert np.all(cliffs.xyz[flatish, 2] > zs - 0.2)
    assert steepness(cliffs.xyz, SteepParams()).steep


def test_rotation_finds_steep_ground(cliffs):
    conservative = PtdParams.preset("conservative")
    ground = lambda p: classify_ground(p, conservative)  # noqa: E731
    steep = cliffs.extra["steep"]
    plain = ground(cliffs.xyz)
    res = classify_rotated(
        cliffs.xyz,
        ground,
        RotationParams(),
        unrotated=plain,
        seeded=lambda p, known: classify_ground(p, conservative, seed_mask=known),
    )
    miss_plain = np.count_nonzero(steep & ~plain) / steep.sum()
    miss_rot = np.count_nonzero(steep & ~res.is_ground) / steep.sum()
    assert miss_rot < miss_plain - 0.2
    assert sum(res.added) > 0 and res.is_ground[plain].all()
    # Both the roof over the lip and ground under it are found somewhere.
    assert np.count_nonzero(res.is_ground & cliffs.extra["covered"]) > 0
    # Type II stays near the unrotated aggressive filter's. Issue 4 asks for at
    # most +1 point; this guards the +3 points measured now (see the benchmark).
    aggressive = classify_ground(cliffs.xyz, PtdParams.preset("aggressive"))
    obj = ~cliffs.is_ground
    t2_rot = np.count_nonzero(res.is_ground & obj) / obj.sum()
    t2_agg = np.count_nonzero(aggressive & obj) / obj.sum()
    assert t2_rot < t2_agg + 0.06


def test_birds_are_not_added_by_rotations(cliffs):
    # Tipping moves a bird 60 m up by 30 m sideways, alone in its cell: it must
    # not come back as ground from a rotated run.
    x0, y0, x1, y1 = cliffs.bounds
    birds = np.column_stack(
        [np.full(5, (x0 + x1) / 2), np.linspace(y0 + 20, y1 - 20, 5), np.full(5, 90.0)]
    )
    xyz = np.vstack([cliffs.xyz, birds])
    conservative = PtdParams.preset("conservative")
    res = classify_rotated(
        xyz, lambda p: classify_ground(p, conservative), RotationParams(edge_margin=0.0)
    )
    assert not res.is_ground[-5:].any()


def test_seed_mask_points_start_the_tin():
    pts = _plane(0.0)[:3000]
    pts[:, 2] += np.where(np.arange(3000) % 2 == 0, 0.0, 5.0)  # every other point 5 m up
    known = np.zeros(3000, bool)
    known[1::2] = True  # claim the raised ones are ground
    plain = classify_ground(pts, PtdParams())
    seeded = classify_ground(pts, PtdParams(), seed_mask=known)
    # the anchored seed grid leaves a few raised points at a data corner (4 of 1500 measured)
    assert plain[1::2].mean() < 0.01
    assert seeded[1::2].sum() > 100  # thinned seeds: one per 2·min_spacing cell at least


def test_lone_low_points_are_no_cliff():
    # Low outliers (multipath) that a ground filter let through: each makes
    # steep facets with its neighbour cells, but stands alone in its height band.
    pts = _plane(0.0)
    rng = np.random.default_rng(3)
    sunk = rng.choice(pts.shape[0], 12, replace=False)
    pts[sunk, 2] -= rng.uniform(3.0, 5.0, 12)
    plain = steepness(pts, SteepParams(support=0, cell=15.0))
    assert plain.steep
    assert steepness(pts, SteepParams(cell=15.0)).facet_share == 0.0
    # A real 25 m step keeps its steep facets: its foot is a floor of many points.
    cliff = _plane(25.0)
    assert (
        steepness(cliff, SteepParams()).facet_share
        == steepness(cliff, SteepParams(support=0)).facet_share
        > 0
    )


def test_rotated_runs_see_only_the_faces(cliffs):
    # With steep_reach and context, each rotated run gets the points near the
    # steep facets of the unrotated ground, not the whole block.
    conservative = PtdParams.preset("conservative")
    plain = classify_ground(cliffs.xyz, conservative)
    sizes = []

    def spy(p):
        sizes.append(p.shape[0])
        return classify_ground(p, conservative)

    res = classify_rotated(cliffs.xyz, spy, RotationParams(context=6.0), unrotated=plain)
    assert len(sizes) == 8 and max(sizes) < 0.8 * cliffs.xyz.shape[0] and min(sizes) > 100
    steep = cliffs.extra["steep"]
    assert (
        np.count_nonzero(steep & res.is_ground)
        > np.count_nonzero(steep & plain) + 0.2 * steep.sum()
    )
    whole = classify_rotated(
        cliffs.xyz,
        lambda p: classify_ground(p, conservative),
        RotationParams(context=None),
        unrotated=plain,
    )
    assert (
        abs(
            int(np.count_nonzero(steep & res.is_ground))
            - int(np.count_nonzero(steep & whole.is_ground))
        )
        < 0.1 * steep.sum()
    )


def test_rolling_ground_cut_by_the_data_edge_is_not_steep():
    # Rolling ground ending a metre or so into a last column of cells: lowest
    # points along cell borders and along the data's edge are nearly collinear,
    # and the thin facets between them tilt with any height difference.
    for seed, width in [(0, 0.8), (1, 1.5), (2, 0.8), (3, 0.8)]:
        rng = np.random.default_rng(seed)
        xy = rng.uniform(0, [150 + width, 136.0], (30000, 2))
        z = (
            0.05 * xy[:, 1]
            + 1.5 * np.sin(xy[:, 1] / 6.0)
            + 0.5 * np.sin(xy[:, 0] / 5)
            + rng.normal(0, 0.1, len(xy))
        )
        test = steepness(np.column_stack([xy + [5e5, 5.4e6], z]), SteepParams())
        assert test.facet_share == 0.0, (seed, test)


def test_bind_ground_seeds_only_stages_that_take_a_seed_mask():
    from terrasift.workers.ground.rotation import bind_ground, can_seed
    from terrasift.workers.registry import get_stage

    ptd, nist = get_stage("ground.ptd"), get_stage("ground.nist")
    assert can_seed(ptd) and not can_seed(nist)
    pts = _plane(0.0)[:3000]
    params = ptd.params.preset("conservative")
    plain, seeded = bind_ground(ptd, params)
    assert np.array_equal(plain(pts), classify_ground(pts, params))
    known = np.zeros(len(pts), dtype=bool)
    known[::7] = True
    assert np.array_equal(seeded(pts, known), classify_ground(pts, params, seed_mask=known))
    plain, seeded = bind_ground(nist, nist.params.preset("conservative"))
    assert seeded is None and plain(pts).dtype == bool


def test_rotation_preset_follows_the_ground_method():
    from terrasift.errors import ParameterError
    from terrasift.jobs.params import rotation_params, stage_params, validate_params

    assert rotation_params({}, "ground.ptd") == RotationParams()
    nist = rotation_params({}, "ground.nist")
    assert (nist.angle, nist.second_angle) == (30.0, 45.0) and not nist.rerun_unrotated
    assert nist.ground_preset == "conservative"
    # job overrides still go on top of the method's preset
    one = rotation_params({"ground.rotation.second_angle": "none"}, "ground.nist")
    assert one.second_angle is None and one.angle == 30.0
    # a preset the stage does not have is an error, not the defaults
    with pytest.raises(ParameterError, match="unknown preset 'ground.ptd'"):
        stage_params({}, "ground.rotation", "ground.ptd")
    # so is a rotation preset the ground method does not have
    with pytest.raises(ParameterError, match="unknown preset 'steep'"):
        validate_params({"ground.rotation.preset": "steep"})


def test_block_rotates_with_the_methods_preset(monkeypatch):
    from terrasift.jobs.params import block_models, validate_params
    from terrasift.tiling.blocks import BlockGrid
    from terrasift.workers import steps
    from terrasift.workers.block import Block
    from terrasift.workers.ground import rotation

    seen = {}
    real = rotation.classify_rotated

    def spy(xyz, ground, params, **kw):
        seen["params"], seen["seeded"], seen["unrotated"] = (
            params,
            kw.get("seeded"),
            kw.get("unrotated"),
        )
        return real(xyz, ground, params.model_copy(update={"directions": 1}), **kw)

    monkeypatch.setattr(rotation, "classify_rotated", spy)
    pts = _plane(25.0)[::4]
    for method, second in (("ptd", None), ("nist", 45.0)):
        seen.clear()
        models = block_models(validate_params({"ground": method, "rotation": "always"}))
        grid = BlockGrid.over(pts.min(0)[:2], pts.max(0)[:2], 0.5, 200.0, 20.0, 2.0)
        core = np.ones(len(pts), bool)
        block = Block(pts, np.zeros(len(pts)), core, grid, 0, 0, 8.0, lambda: None)
        steps.ground_step(block, models)
        assert seen["params"].second_angle == second
        assert (seen["seeded"] is not None) == (method == "ptd")
        assert (seen["unrotated"] is not None) == (
            method == "nist"
        )  # nist keeps its default labels


def test_a_second_tip_finds_more_of_the_faces_without_face_evidence(cliffs):
    # Without face evidence and with the 4 m reach, tipped by 30° only the
    # overhang stays steeper than ground.nist follows; a second tip of 45°
    # finds it (the rerun conservative unrotated run drops terrain the default
    # run keeps). The preset has one tip since face evidence judges additions.
    from terrasift.jobs.params import stage_params
    from terrasift.workers.ground.rotation import bind_ground
    from terrasift.workers.registry import get_stage

    stage = get_stage("ground.nist")
    default = stage.run(cliffs.xyz, stage.params.preset("default"))
    plain, _ = bind_ground(stage, stage.params.preset("conservative"))
    steep = cliffs.extra["steep"]
    # The angles alone: both with the 4 m reach and no face evidence.
    old = {"face_evidence": False, "steep_reach": 4.0, "context": 6.0}
    seed = classify_rotated(cliffs.xyz, plain, RotationParams(**old))
    rp = stage_params({}, "ground.rotation", "ground.nist").model_copy(
        update={**old, "second_angle": 45.0}
    )
    own = classify_rotated(cliffs.xyz, plain, rp, unrotated=default)
    # Measured 0.052 and 0.049 since slivers along the data's edge cast no
    # screening vote (``screen_rim``: the tipped views keep more of their rims);
    # 0.10 and 0.077 before; 0.74 and 0.27 before raised segments reaching the
    # data's edge along 20 m were kept (``raised_edge``): the tipped views' rims.
    missed_seed = np.mean(~seed.is_ground[steep])
    missed_own = np.mean(~own.is_ground[steep])
    assert missed_own < missed_seed and missed_own < 0.15
    assert len(own.added) == 16 and len(seed.added) == 8


def test_second_angle_adds_a_run_per_direction():
    pts = _plane(0.0)[:500]
    tips = []

    def fake_ground(p):
        tips.append(float(np.ptp(p[:, 2])))
        return p[:, 2] < np.median(p[:, 2])

    res = classify_rotated(
        pts,
        fake_ground,
        RotationParams(directions=2, angle=10, second_angle=40, context=None, face_evidence=False),
    )
    assert len(tips) == 5 and len(res.added) == 4
    assert max(tips[1:3]) < min(tips[3:])  # 10° runs first, then the steeper 40° ones


def test_landform_tile_truth():
    from terrasift.synthetic.landforms import House, LandformSpec, Mesa, make_landforms

    spec = LandformSpec(
        size=60.0,
        density=3.0,
        slope=(0.05, 0.0),
        mesas=[Mesa(20.0, 30.0, 8.0, 15.0, angle=85.0, talus=0.2)],
        houses=[House(45.0, 30.0, 10.0, 12.0, 30.0, 8.0, 3.0)],
        face_stems=10,
        max_scan_angle=30.0,
    )
    scene = make_landforms(spec, seed=3)
    e = scene.extra
    xy = scene.xyz[:, :2] - scene.bounds[:2]
    assert np.all((xy >= -0.2) & (xy <= 60.2))  # noise of 3 cm about the edges
    # Oblique beams sample the mesa's faces: steep ground, all of it on the landform's flanks.
    r = np.hypot(xy[:, 0] - 20.0, xy[:, 1] - 30.0)
    assert e["steep"].sum() > 30 and np.all(r[e["steep"]] < 8.0 * 1.15 + 3.0)
    top = e["landform"] & (scene.xyz[:, 2] > 100.0 + 0.05 * 20.0 + 14.0)
    assert top.sum() > 0.5 * 3.0 * np.pi * 6.8**2
    # Roof and wall points are buildings, never ground or landform.
    bldg = scene.truth == 6
    assert bldg.sum() > 0.5 * 3.0 * 120 and not np.any(e["landform"] & bldg)
    assert np.all(np.abs(scene.xyz[bldg, 0] - scene.bounds[0] - 45.0) < 9.0)
    assert np.any(e["near_face"])


def test_landform_rule_keeps_mesas_and_hills_and_drops_buildings():
    from terrasift.synthetic.landforms import Hill, House, LandformSpec, Mesa, make_landforms
    from terrasift.workers.ground.landforms import LandformParams, restore_landforms
    from terrasift.workers.ground.nist import NistParams
    from terrasift.workers.ground.nist import classify_ground as nist

    spec = LandformSpec(
        size=120.0,
        density=2.0,
        slope=(0.08, -0.05),
        mesas=[Mesa(35.0, 40.0, 12.0, 20.0, angle=80.0, talus=0.3)],
        hills=[Hill(35.0, 95.0, 14.0, 16.0)],
        houses=[
            House(90.0, 40.0, 24.0, 16.0, 20.0, 10.0),
            House(90.0, 90.0, 18.0, 14.0, 0.0, 7.0, 3.0),
        ],
        tree_density=0.0,
        bush_density=0.0,
        face_stems=0,
    )
    scene = make_landforms(spec, seed=5)
    before = nist(scene.xyz, NistParams())
    after = restore_landforms(scene.xyz, before, LandformParams())
    land, bldg = scene.extra["landform"], scene.truth == 6
    mesa = land & (np.hypot(*(scene.xyz[:, :2] - scene.bounds[:2] - (35.0, 40.0)).T) < 20.0)
    # The filter takes the mesa for a building (the hill too, in part, as its bins fall);
    # the rule gives them back.
    assert np.mean(before[mesa]) < 0.3 and np.mean(after[land]) > 0.8
    assert not np.any(after[bldg])
    assert (
        not restore_landforms(scene.xyz, before, LandformParams(enabled=False))[land].mean() > 0.6
    )


def test_face_evidence_keeps_faces_and_drops_crowns_beside_them():
    from terrasift.workers.ground.rotation import _on_faces

    rng = np.random.default_rng(7)
    # Level ground (x < 20), a vertical face at x = 20 up to 15 m, a crown at its foot.
    floor = np.column_stack([rng.uniform(0, 20, 3000), rng.uniform(0, 30, 3000), np.zeros(3000)])
    face = np.column_stack(
        [np.full(2000, 20.0), rng.uniform(0, 30, 2000), rng.uniform(0.2, 15, 2000)]
    )
    crown = rng.normal([15.0, 15.0, 5.0], [1.5, 1.5, 1.5], (600, 3))
    xyz = np.vstack([floor, face, crown]) + rng.normal(0, 0.02, (5600, 3))
    base = np.r_[np.ones(3000, bool), np.zeros(2600, bool)]
    cand = ~base
    foot = xyz.copy()
    foot[:, 2] = np.minimum(xyz[:, 2], 0.0)
    kept = _on_faces(xyz, base, cand, foot, RotationParams())
    assert kept[3000:5000].mean() > 0.8  # 0.83: its foot and top mix with the floor and the rim
    assert kept[5000:].mean() < 0.1
    # A face standing apart from any ground (a wall's top half floating) is not linked.
    lifted = xyz.copy()
    lifted[3000:5000, 2] += 20.0
    assert _on_faces(lifted, base, cand, foot, RotationParams())[3000:5000].mean() < 0.1


def test_runs_see_only_the_faces_looking_their_way():
    # A straight step rising toward +x (east) looks west: only the runs tipped
    # toward 270° and its neighbours (225°, 315°: the step's facets, summed over
    # 6 m, look 260–280°) see points; without the window every direction runs
    # on the points near the step.
    pts = _plane(25.0)
    base = pts[:, 2] < 0.02 * (pts[:, 0] - 5e5) + 0.5 + np.where(pts[:, 0] > 5e5 + 75, 25.0, 0.0)
    sizes: dict[str, list[int]] = {"window": [], "none": []}
    for key, window in (("window", 45.0), ("none", None)):

        def spy(p, key=key):
            sizes[key].append(p.shape[0])
            return np.zeros(p.shape[0], dtype=bool)

        params = RotationParams(aspect_window=window, face_evidence=False)
        res = classify_rotated(pts, spy, params, unrotated=base)
        assert len(res.added) == 8
    assert 1 <= len(sizes["window"]) <= 3 and len(sizes["none"]) == 8
    assert sum(sizes["window"]) < 0.5 * sum(sizes["none"])
    # A run sees the step with 20 m on either side (40 of 150 m), not the block.
    assert 0.1 * len(pts) < max(sizes["window"]) < 0.4 * len(pts)


def test_a_face_over_a_cave_is_found_to_its_top():
    # A 40 m face rising over a 14 m deep cave: the lowest ground under it is
    # the cave's floor, 6.5 m below the lip. A height band about that floor
    # (max_lift 30 m) cut the face's upper part; the face evidence alone keeps it.
    cave = (
        (0.0, 0.0),
        (40.0, 3.0),
        (62.0, 3.5),
        (62.0, 9.0),
        (48.0, 10.0),
        (49.0, 50.0),
        (120.0, 55.0),
        (125.0, 28.0),
        (136.0, 21.0),
        (225.0, 24.0),
    )
    scene = make_cliffs(length=16, density=4, profile=cave, seed=3, tree_density=0, bush_density=0)
    face = np.nan_to_num(scene.extra["face_angle"])
    upper = scene.extra["steep"] & (face > 80) & (scene.xyz[:, 2] > scene.xyz[:, 2].min() + 35)
    conservative = PtdParams.preset("conservative")
    ground = lambda p: classify_ground(p, conservative)  # noqa: E731
    base = ground(scene.xyz)
    found = {
        lift: classify_rotated(scene.xyz, ground, RotationParams(max_lift=lift), unrotated=base)
        .is_ground[upper]
        .mean()
        for lift in (None, 30.0)
    }
    assert upper.sum() > 100 and not base[upper].any()
    assert found[None] > 0.5 and found[30.0] < 0.1, found


def test_rotated_runs_give_back_a_tipped_mesa():
    # Tipped by 30°, a mesa is still a raised body to the filter: the runs of
    # the first tip take the landform rule after the filter (``restore``).
    from terrasift.synthetic.landforms import LandformSpec, Mesa, make_landforms
    from terrasift.workers.ground.landforms import LandformParams, restore_landforms
    from terrasift.workers.ground.rotation import bind_ground
    from terrasift.workers.registry import get_stage

    spec = LandformSpec(
        size=120.0,
        density=2.0,
        slope=(0.08, -0.05),
        mesas=[Mesa(60.0, 60.0, 15.0, 25.0, angle=80.0, talus=0.3)],
        tree_density=0.0,
        bush_density=0.0,
        face_stems=0,
    )
    scene = make_landforms(spec, seed=5)
    stage = get_stage("ground.nist")
    plain, _ = bind_ground(stage, stage.params.preset("conservative"))
    c = scene.xyz.mean(axis=0)
    tipped = (scene.xyz - c) @ rotation_matrix(270.0, 30.0).T + c
    steep = scene.extra["steep"]
    before = plain(tipped)
    after = restore_landforms(tipped, before, LandformParams())
    assert np.mean(before[steep]) < 0.2 and np.mean(after[steep]) > 0.4
    assert after[before].all()
    # classify_rotated calls it after the runs of the first tip only
    tips = []

    def ground(p: np.ndarray) -> np.ndarray:
        return np.zeros(len(p), dtype=bool)

    def restore(p: np.ndarray, got: np.ndarray) -> np.ndarray:
        tips.append(len(p))
        return got

    params = RotationParams(second_angle=45.0, context=None, aspect_window=None)
    classify_rotated(tipped, ground, params, unrotated=before, restore=restore)
    assert len(tips) == params.directions


def test_views_find_a_face_below_a_plateau_the_filter_lost():
    # The filter kept only the low side of a 25 m step (it lost the plateau
    # above, as a raised body cut by the data's edge): its ground labels have
    # no step, so no run saw the face. The lowest of all points still steps
    # there (``anchor_all``); a crown 8 m over kept ground does not count.
    rng = np.random.default_rng(1)
    pts = _plane(25.0)
    crown = np.column_stack(
        [rng.uniform(5e5 + 27, 5e5 + 33, 600), rng.uniform(5.4e6 + 72, 5.4e6 + 78, 600)]
    )
    crown_z = 0.02 * (crown[:, 0] - 5e5) + 8.0 + rng.uniform(0, 4, 600)
    under = (np.abs(pts[:, 0] - 5e5 - 30) < 3) & (np.abs(pts[:, 1] - 5.4e6 - 75) < 3)
    pts = np.vstack([pts[~under], np.column_stack([crown, crown_z])])
    base = (pts[:, 0] < 5e5 + 75) & (pts[:, 2] < 0.02 * (pts[:, 0] - 5e5) + 0.5)
    seen: dict[str, list[np.ndarray]] = {"all": [], "ground": []}
    for key, anchor in (("all", 10.0), ("ground", None)):

        def spy(p, key=key):
            seen[key].append(p)
            return np.zeros(p.shape[0], dtype=bool)

        params = RotationParams(anchor_all=anchor, face_evidence=False)
        classify_rotated(pts, spy, params, unrotated=base)
    assert seen["ground"] == []
    assert 1 <= len(seen["all"]) <= 3
    # The runs see the step with 20 m either side, not the crown 45 m off it.
    assert 0.1 * len(pts) < max(len(p) for p in seen["all"]) < 0.4 * len(pts)


def test_landform_cells_hold_ground_under_crowns_at_the_foot_of_faces():
    # At 2 pulses/m² a cell of 1.5 mean spacings holds two points: under a
    # crown at the foot of a face its lowest point is often a crown return,
    # the crown joins the raised body and is given back with it. Cells of 2
    # spacings hold ground under more crowns; the mesa itself stays.
    from terrasift.synthetic.landforms import LandformSpec, Mesa, make_landforms
    from terrasift.workers.ground.landforms import LandformParams, restore_landforms
    from terrasift.workers.ground.nist import NistParams
    from terrasift.workers.ground.nist import classify_ground as nist

    spec = LandformSpec(
        size=80.0,
        density=2.0,
        slope=(0.05, 0.02),
        mesas=[Mesa(40.0, 40.0, 15.0, 25.0, angle=80.0, talus=0.2)],
        tree_density=0.0,
        bush_density=0.0,
        face_stems=40,
        max_scan_angle=8.0,
    )
    scene = make_landforms(spec, seed=2)
    last = scene.return_number >= scene.number_of_returns
    before = nist(scene.xyz, NistParams())
    tall = (scene.truth == 4) | (scene.truth == 5)
    land = scene.extra["landform"]
    got = {
        k: restore_landforms(scene.xyz, before, LandformParams(spacings=k), last)
        for k in (1.5, 2.0)
    }
    assert tall.sum() > 500 and np.mean(before[land]) < 0.3
    crowns = {k: int(np.count_nonzero(g & tall & ~before)) for k, g in got.items()}
    assert crowns[2.0] < 0.7 * crowns[1.5], crowns
    assert np.mean(got[2.0][land]) > 0.85


def test_a_thinly_sampled_face_is_linked_by_its_own_spacing():
    from terrasift.workers.ground.rotation import _on_faces

    rng = np.random.default_rng(3)
    # Level ground (x < 20, 5 pts/m²) and a vertical face at x = 20 up to 15 m that
    # the beams graze: 0.15 pts/m², its points metres apart.
    floor = np.column_stack([rng.uniform(0, 20, 3000), rng.uniform(0, 30, 3000), np.zeros(3000)])
    face = np.column_stack([np.full(70, 20.0), rng.uniform(0, 30, 70), rng.uniform(0.5, 15, 70)])
    # A dense smooth patch (a trunk's side) 5 m in front of the face, 6 m up: smooth and
    # steep like a face, but its returns crowd and nothing ground lies within its reach.
    patch = np.column_stack([np.full(40, 15.0), rng.uniform(14, 15, 40), rng.uniform(6, 7, 40)])
    xyz = np.vstack([floor, face, patch]) + rng.normal(0, 0.02, (3110, 3))
    base = np.r_[np.ones(3000, bool), np.zeros(110, bool)]
    foot = xyz.copy()
    foot[:, 2] = np.minimum(xyz[:, 2], 0.0)
    own = _on_faces(xyz, base, ~base, foot, RotationParams())
    one = _on_faces(xyz, base, ~base, foot, RotationParams(face_local_link=False))
    # 0.74 linked of the 0.79 that lie on a surface; 0.27 with one reach for all
    assert own[3000:3070].mean() > 0.6
    assert one[3000:3070].mean() < 0.5 * own[3000:3070].mean()
    # The patch passes the surface tests; the face's long reach does not pull it in.
    assert not own[3070:].any()
