"""Scan geometry measured from the points against the generator's known scanner."""

from __future__ import annotations

import numpy as np
import pytest

from terrasift.synthetic.scan import make_scan
from terrasift.workers.scan_geometry import (
    ScanGeometry,
    coordinate_scale,
    measure_scan_geometry,
    pool_footprints,
    ramp_sectors,
)


@pytest.mark.parametrize(
    ("step", "footprint", "noise", "scale"),
    [(0.3, 3.0, 0.01, 0.01), (0.12, 1.0, 0.003, 0.001), (0.4, 2.0, 0.006, 0.0)],
)
def test_measured_geometry_matches_the_scanner(step, footprint, noise, scale):
    s = make_scan(
        step_deg=step,
        footprint_steps=footprint,
        range_noise=noise,
        las_scale=scale,
        azimuth_deg=(-40.0, 40.0),
        n_boards=6,
        n_poles=6,
        object_range=(3.0, 30.0),
        seed=3,
    )
    g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
    assert g is not None
    assert g.step_az == pytest.approx(step, rel=0.01)
    assert g.step_el == pytest.approx(step, rel=0.01)
    assert g.las_scale == pytest.approx(scale, abs=1e-9)
    assert noise * 0.8 < g.range_noise < noise * 1.4, g
    # Ramps of blended returns, over the edges that show one (where a third surface far
    # behind shares the footprint the nearest answers alone, with no ramp).
    assert footprint - 0.3 < g.footprint_steps < footprint + 0.3, g
    assert g.footprint == pytest.approx(g.footprint_steps * g.step_az)
    assert set(g.how) == {"las_scale", "step", "range_noise", "footprint", "surface_sigma"}
    total = np.sqrt(noise**2 + scale**2 / 12.0)
    # the scatter on surfaces: the noise and quantisation, edges and blends left out
    # (0.986-1.006 of it; the median residual reads 1.03-1.18)
    assert g.surface_sigma == pytest.approx(total, rel=0.04)


def test_stated_footprint_and_scale_are_kept():
    s = make_scan(step_deg=0.3, azimuth_deg=(-30.0, 30.0), n_boards=3, n_poles=3, seed=1)
    g = measure_scan_geometry(s.xyz - s.origin, footprint=0.9, las_scale=0.002)
    assert g.footprint == 0.9 and g.how["footprint"] == "stated"
    assert g.las_scale == 0.002 and g.how["las_scale"] == "stated"
    assert g.footprint_steps == pytest.approx(3.0, rel=0.02)


def test_footprint_from_edges_away_from_the_middle_sector(monkeypatch):
    # A position standing beside a scene (another position's) sees its objects at one
    # side of a wide view; the middle sector of the sample holds ground only. The
    # footprint is measured on sectors spread over the whole scan.
    from terrasift.synthetic.scan import Board
    from terrasift.workers import scan_geometry as sg

    def facing(az_deg: float, dist: float, half: float, z1: float) -> Board:
        a = np.radians(az_deg)
        return Board(dist * np.cos(a), dist * np.sin(a), -np.cos(a), -np.sin(a), half, 0.0, z1)

    boards = [facing(-33.0, 8.0, 0.4, 1.0), facing(-25.0, 7.0, 0.3, 1.2)]
    walls = [facing(-30.0, 9.5, 1.6, 2.5)]
    s = make_scan(
        step_deg=0.3,
        footprint_steps=2.0,
        azimuth_deg=(-40.0, 40.0),
        elevation_deg=(-20.0, 10.0),
        max_range=20.0,
        scene=(boards, [], walls),
        seed=2,
    )
    monkeypatch.setattr(sg, "MAX_SAMPLE", 4_000)
    assert len(s) > 4 * sg.MAX_SAMPLE
    g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
    assert g is not None and not g.how["footprint"].startswith("no mixing"), g.how
    assert 1.6 < g.footprint_steps < 2.4, g


def test_coordinate_scale():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 50, (5000, 3)) + [500_000.0, 5_400_000.0, 100.0]
    assert coordinate_scale(xyz) == 0.0
    assert coordinate_scale(np.round(xyz / 0.005) * 0.005) == pytest.approx(0.005)
    assert coordinate_scale(np.round(xyz / 0.01) * 0.01) == pytest.approx(0.01)


def test_too_few_points():
    assert measure_scan_geometry(np.ones((10, 3))) is None


def test_refine_step_removes_the_drift_of_a_step_slightly_off():
    from terrasift.workers.scan_geometry import refine_step

    # 2000 scan lines 0.05° apart: a step off by 0.4 % drifts 8 lines across them.
    rng = np.random.default_rng(3)
    step = np.radians(0.05)
    a = 0.3 + step * rng.integers(0, 2000, 30_000) + rng.normal(0.0, 0.05 * step, 30_000)
    s = refine_step(a, step * 1.004)
    assert abs(s / step - 1) < 2e-5
    # no grid in uniform angles: the estimate is returned unchanged
    u = rng.uniform(0.0, 1.0, 5000)
    assert refine_step(u, step) == step


def test_refine_step_weights_angles_by_their_quantisation_blur():
    from terrasift.workers.scan_geometry import refine_step

    # 1 cm coordinates at a 0.06° step: near returns are blurred by about half a step
    # and the nearest-neighbour spacing runs 8 % long; the few far, sharp ones carry the grid.
    rng = np.random.default_rng(5)
    step = np.radians(0.06)
    n_near, n_far = 20_000, 1_500
    blur = np.r_[np.full(n_near, 0.45 * step), np.full(n_far, 0.05 * step)]
    a = 0.2 + step * rng.integers(0, 300, n_near + n_far) + rng.normal(0.0, blur)
    assert refine_step(a, step * 1.08) == step * 1.08  # unweighted: no grid fits
    assert abs(refine_step(a, step * 1.08, blur=blur) / step - 1) < 1e-3


def test_one_centimetre_coordinates_at_a_fine_step():
    # 1 cm coordinates at 0.06°: the returns nearer than ~30 m are blurred by 0.1-0.5 step.
    # The step comes from the farthest returns, weighted by their blur, and the footprint
    # from edges among returns blurred by under 0.15 step (no sharp return shows one).
    s = make_scan(
        step_deg=0.06,
        footprint_steps=2.5,
        range_noise=0.005,
        las_scale=0.01,
        azimuth_deg=(-6.0, 6.0),
        elevation_deg=(-12.0, 6.0),
        n_boards=3,
        n_poles=3,
        object_range=(6.0, 25.0),
        seed=2,
    )
    g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
    assert g is not None  # the farthest half alone showed no regular grid
    assert g.step_az == pytest.approx(0.06, rel=0.002)
    assert g.step_el == pytest.approx(0.06, rel=0.002)
    assert 1.7 < g.footprint_steps < 3.0, g  # measured 2.0 (one step assumed before)
    assert "under 0.15 step" in g.how["footprint"]


def test_steps_from_the_firing_order_where_the_angles_show_no_grid(near_coarse_scan):
    # 1 cm coordinates at 0.035° with every return within about 14 m (median 4.6 m): each
    # angle is blurred by half a step and more, so no share of the returns shows the grid
    # and the angles alone measure nothing; the GPS time still orders the pulses.
    s = near_coarse_scan
    rel = s.xyz - s.origin
    assert measure_scan_geometry(rel, absolute=s.xyz) is None
    g = measure_scan_geometry(rel, absolute=s.xyz, gps_time=s.gps_time)
    assert g is not None
    assert g.step_az == pytest.approx(0.035, rel=0.01)  # measured 0.03486
    assert g.step_el == pytest.approx(0.035, rel=0.01)  # measured 0.03500
    assert g.how["step"].startswith("firing order from GPS time")
    # shuffled points give the same steps (the pulse numbers order them; 7e-6 apart)
    o = np.random.default_rng(1).permutation(rel.shape[0])
    g2 = measure_scan_geometry(rel[o], absolute=s.xyz[o], gps_time=s.gps_time[o])
    assert g2 is not None and g2.step_az == pytest.approx(g.step_az, rel=1e-4)


def test_job_geometry_per_scan_position_from_all_shards(tmp_path):
    from terrasift.jobs.scan import job_geometry, measure_job_geometry
    from terrasift.tiling.blocks import SHARD_DTYPE
    from terrasift.workers.mixed import MixedParams

    # two scan positions with different steps, their points spread over shard files of
    # two tile parts, halo copies (core 0) among them; each position is measured on its
    # own points only, as the stage alone measures the whole scan
    scans = [
        make_scan(step_deg=0.3, azimuth_deg=(-30.0, 30.0), n_boards=3, n_poles=3, seed=1),
        make_scan(step_deg=0.2, azimuth_deg=(-20.0, 20.0), n_boards=3, n_poles=3, seed=2),
    ]
    shift = np.array([[0.0, 0.0, 0.0], [60.0, 5.0, 0.0]])
    parts = [tmp_path / "a", tmp_path / "b"]
    for d in parts:
        d.mkdir()
    for k, s in enumerate(scans):
        xyz = s.xyz + shift[k]
        rec = np.zeros(len(xyz), SHARD_DTYPE)
        rec["x"], rec["y"], rec["z"] = xyz.T
        rec["scan_id"], rec["core"] = k, 1
        half = len(rec) // 2
        rec[:half].tofile(parts[0] / f"{k}_0.bin")
        rec[half:].tofile(parts[1] / f"{k}_1.bin")
        halo = rec[:500].copy()
        halo["core"] = 0
        halo.tofile(parts[1] / f"{1 - k}_9.bin")  # copies in another block: not counted
    origins = [tuple(s.origin + shift[k]) for k, s in enumerate(scans)]
    found = measure_job_geometry(parts, origins, MixedParams())
    geo = job_geometry(found)
    assert geo is not None and len(geo) == 2
    for k, s in enumerate(scans):
        own = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz + shift[k])
        assert geo[k].n_points == own.n_points == len(s)
        assert geo[k].step_az == pytest.approx(own.step_az, rel=1e-4)
        assert geo[k].footprint_steps == pytest.approx(own.footprint_steps, rel=1e-3)
        assert "once per job" in geo[k].how["scope"]
    assert geo[0].step_az == pytest.approx(0.3, rel=0.01)
    assert geo[1].step_az == pytest.approx(0.2, rel=0.01)


def test_geometry_does_not_depend_on_point_order_and_job_takes_the_stage_sector(tmp_path):
    # a job reads a position's points block by block: the measurement must not depend on
    # their order, and over MAX_SAMPLE points the job takes the very sector the stage does
    from terrasift.jobs.scan import job_geometry, measure_job_geometry
    from terrasift.tiling.blocks import SHARD_DTYPE
    from terrasift.workers import scan_geometry as sg
    from terrasift.workers.mixed import MixedParams

    s = make_scan(step_deg=0.15, azimuth_deg=(-20.0, 20.0), n_boards=3, n_poles=3, seed=6)
    assert 30_000 < len(s) < sg.MAX_SAMPLE
    rel = s.xyz - s.origin
    perm = np.random.default_rng(0).permutation(len(s))
    whole = measure_scan_geometry(rel, absolute=s.xyz)
    assert measure_scan_geometry(rel[perm], absolute=s.xyz[perm]) == whole
    old = sg.MAX_SAMPLE
    try:
        sg.MAX_SAMPLE = 16_000  # the sector is a part of the scan
        a = measure_scan_geometry(rel, absolute=s.xyz)
        rec = np.zeros(len(s), SHARD_DTYPE)
        rec["x"], rec["y"], rec["z"] = s.xyz[perm].T
        rec["core"] = 1
        (tmp_path / "p").mkdir()
        rec[: len(s) // 3].tofile(tmp_path / "p" / "0_0.bin")
        rec[len(s) // 3 :].tofile(tmp_path / "p" / "1_0.bin")
        import terrasift.jobs.scan as js

        js.MAX_SAMPLE = 16_000
        (g,) = job_geometry(measure_job_geometry([tmp_path / "p"], [s.origin], MixedParams()))
    finally:
        sg.MAX_SAMPLE = old
        js.MAX_SAMPLE = old
    assert g.n_points == a.n_points == 16_000
    # the footprint on the same sectors spread over the scan
    assert g.footprint_steps == pytest.approx(a.footprint_steps, rel=1e-5)
    assert g.range_sigma == pytest.approx(a.range_sigma, rel=1e-4)
    assert g.step_az == pytest.approx(a.step_az, rel=1e-5)


def _geo(step: float, steps: float, edges: int, how: str = "mean ramp") -> ScanGeometry:
    return ScanGeometry(
        step_az=step,
        step_el=step,
        range_noise=0.003,
        range_sigma=0.003,
        las_scale=0.001,
        footprint=steps * step,
        footprint_steps=steps,
        n_points=1000,
        how={"footprint": how},
        footprint_edges=edges,
    )


def test_footprints_pooled_over_positions_of_one_scanner():
    # a position beside the scene measured its footprint on 10 edges, the one facing it
    # on 200: both get the mean over all 210, and so does a position of that step that
    # showed no ramp (it has the same beam; it kept one step before); another step
    # (another scanner setting) and a stated footprint keep their own
    geos = [
        _geo(0.1, 2.0, 200),
        _geo(0.1005, 1.0, 10),
        _geo(0.2, 3.0, 50),
        _geo(0.1, 1.5, 0, "stated"),
        _geo(0.1, 1.0, 0, "no mixing edge measured: one step assumed"),
        None,
    ]
    out = pool_footprints(geos)
    want = (2.0 * 200 + 1.0 * 10) / 210
    assert out[0].footprint_steps == pytest.approx(want)
    assert out[1].footprint_steps == pytest.approx(want)
    assert out[1].footprint == pytest.approx(want * 0.1005)
    assert "pooled over the positions [0, 1]" in out[1].how["footprint"]
    assert out[4].footprint_steps == pytest.approx(want)
    assert out[4].footprint == pytest.approx(want * 0.1)
    assert "none measured at this position" in out[4].how["footprint"]
    assert out[2:4] == geos[2:4] and out[5] is None
    assert pool_footprints(geos[2:]) == geos[2:]


def test_footprint_not_shortened_by_poles_narrower_than_it():
    # 0.11-0.12° steps, footprints of 2.5-2.7 steps, poles at 3-15 m a few beams wide:
    # the plateau of blends before a pole narrower than the footprint sat between two
    # ramps about the pole's width long, and counted as two edges, so the mean ran 0.77
    # of the true footprint on both scans. Edges need flanks of three beams on a surface.
    for step, fp, noise in ((0.12, 2.5, 0.007), (0.11, 2.7, 0.004)):
        s = make_scan(
            step_deg=step,
            footprint_steps=fp,
            range_noise=noise,
            las_scale=0.002,
            azimuth_deg=(-30.0, 30.0),
            elevation_deg=(-15.0, 5.0),
            n_boards=6,
            n_poles=12,
            seed=0,
        )
        g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
        assert g is not None
        assert 0.9 * fp < g.footprint_steps < 1.1 * fp, g.footprint_steps


def test_stage_and_job_pool_the_footprint_of_positions_with_one_step(tmp_path):
    from terrasift.jobs.scan import job_geometry, measure_job_geometry
    from terrasift.tiling.blocks import SHARD_DTYPE
    from terrasift.workers.mixed import MixedParams, mark_mixed

    kw = dict(step_deg=0.3, footprint_steps=2.5, azimuth_deg=(-30.0, 30.0), n_poles=2)
    scans = [make_scan(n_boards=6, seed=1, **kw), make_scan(n_boards=2, seed=2, **kw)]
    own = [measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz) for s in scans]
    assert own[0].footprint_steps != pytest.approx(own[1].footprint_steps, abs=0.01)
    n = own[0].footprint_edges + own[1].footprint_edges
    want = sum(g.footprint_steps * g.footprint_edges for g in own) / n
    shift = np.array([[0.0, 0.0, 0.0], [60.0, 5.0, 0.0]])
    xyz = np.vstack([s.xyz + shift[k] for k, s in enumerate(scans)])
    ids = np.repeat([0, 1], [len(s) for s in scans])
    origins = np.vstack([s.origin + shift[k] for k, s in enumerate(scans)])
    res = mark_mixed(xyz, MixedParams(), origins, ids)
    for g in res.geometry:
        assert g["measured"]["footprint_steps"] == pytest.approx(want, rel=1e-4)
    (tmp_path / "p").mkdir()
    rec = np.zeros(len(xyz), SHARD_DTYPE)
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["scan_id"], rec["core"] = ids, 1
    rec.tofile(tmp_path / "p" / "0_0.bin")
    geo = job_geometry(measure_job_geometry([tmp_path / "p"], origins, MixedParams()))
    assert geo is not None
    assert [g.footprint_steps for g in geo] == pytest.approx([want, want], rel=1e-3)


def _one_cm_fine_step_scan(seed: int):
    # report 7806's scanner: 1 cm coordinates at a 0.0301° step, every return within
    # 41 m, so no angle is blurred by under a tenth of a step (that needs 55 m)
    return make_scan(
        step_deg=0.0301,
        footprint_steps=1.4,
        range_noise=0.007,
        las_scale=0.01,
        azimuth_deg=(-2.2, 2.2),
        elevation_deg=(-20.0, 5.0),
        mast_height=2.0,
        sub_rays=(3, 3),
        n_boards=2,
        n_poles=2,
        object_range=(3.0, 34.0),
        seed=seed,
    )


@pytest.mark.parametrize("seed", [0, 2])
def test_step_from_the_octave_when_no_grid_fits_near_the_blurred_spacing(seed):
    # The nearest-neighbour spacing along azimuth runs 16-25 % long (0.0350°, 0.0378°),
    # the fit within 20 % of it finds no grid and kept it. The octave about the spacing
    # holds the step and neither its half nor its double.
    s = _one_cm_fine_step_scan(seed)
    g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
    assert g is not None
    assert g.step_az == pytest.approx(0.0301, rel=0.005)
    assert "octave" in g.how["step_az"]


def test_footprint_from_returns_whose_quantisation_box_spans_under_a_step():
    # The same scanner: returns blurred by under 0.2 step show no regular grid (80 % within
    # a quarter step), so no ramp was measured and one step was assumed. Each return
    # whose box spans under a step lies on the line nearest it: the ramps give the beam.
    s = _one_cm_fine_step_scan(4)
    g = measure_scan_geometry(s.xyz - s.origin, absolute=s.xyz)
    assert g is not None
    assert 1.2 < g.footprint_steps < 1.7, g  # 1.4 drawn
    assert "quantisation box" in g.how["footprint"]


def test_a_position_with_no_grid_takes_the_steps_of_one_that_holds_its_returns(
    near_coarse_scan,
):
    # report 8008: one position sees every return within about 10 m with 1 cm coordinates
    # at 0.035°, so its angles show no grid; another position of the tile, looking farther,
    # measures the steps. Its steps are lent when 1 / (step_az · step_el) matches the
    # returns per square radian of both positions; a lender 8 % short in azimuth (report
    # 7304's, measured on blurred angles) is refused and the position keeps no geometry.
    from dataclasses import replace

    from terrasift.workers.scan_geometry import angular_density, lenders

    s = near_coarse_scan
    rel = s.xyz - s.origin
    assert measure_scan_geometry(rel, absolute=s.xyz) is None
    far = make_scan(
        step_deg=0.035,
        footprint_steps=2.0,
        azimuth_deg=(-2.0, 2.0),
        elevation_deg=(-8.0, 4.0),
        n_boards=2,
        n_poles=1,
        object_range=(14.0, 30.0),
        las_scale=0.01,
        seed=4,
    )
    lender = measure_scan_geometry(far.xyz - far.origin, absolute=far.xyz)
    assert lender is not None and lender.step_az == pytest.approx(0.035, rel=0.01)
    assert lender.density * np.radians(lender.step_az) * np.radians(lender.step_el) == (
        pytest.approx(1.0, abs=0.02)
    )
    g = measure_scan_geometry(rel, absolute=s.xyz, lenders=lenders([None, lender]))
    assert g is not None
    assert (g.step_az, g.step_el) == (lender.step_az, lender.step_el)
    assert g.how["step"].startswith("lent by another position")
    assert g.las_scale == pytest.approx(0.01)
    short = replace(lender, step_az=0.92 * lender.step_az)
    assert measure_scan_geometry(rel, absolute=s.xyz, lenders=[short]) is None
    # the count checks the product of both steps, whatever their blur
    r = np.linalg.norm(rel, axis=1)
    az, el = np.arctan2(rel[:, 1], rel[:, 0]), np.arcsin(rel[:, 2] / r)
    st = np.radians(0.035)
    assert angular_density(az, el, st, st) * st * st == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("case", ["regular", "octave"])
def test_sectors_cut_here_give_the_geometry_of_the_same_sectors_passed_in(case):
    # Cut here, the sectors' angles are taken from the angles computed for the whole scan;
    # passed in (a job's), they are computed from their points. Both give one geometry to
    # the bit, a return at the sensor (left out) included.
    if case == "regular":
        s = make_scan(
            step_deg=0.12,
            footprint_steps=2.0,
            range_noise=0.003,
            las_scale=0.001,
            azimuth_deg=(-40.0, 40.0),
            n_boards=6,
            n_poles=6,
            object_range=(3.0, 30.0),
            seed=3,
        )
    else:
        s = _one_cm_fine_step_scan(0)
    rel = np.vstack([s.xyz - s.origin, np.zeros((1, 3))])
    absolute = np.vstack([s.xyz, s.origin[None, :]])
    here = measure_scan_geometry(rel, absolute=absolute)
    kept = rel[np.linalg.norm(rel, axis=1) > 1e-6]
    az = np.arctan2(kept[:, 1], kept[:, 0])
    o = np.argsort(az, kind="stable")
    cut = [kept[o[a:b]] for a, b in ramp_sectors(az.size)]
    assert len(cut) > 1  # several sectors, each cut in azimuth order
    given = measure_scan_geometry(rel, absolute=absolute, sectors=cut)
    assert here is not None and given is not None
    assert here.footprint_edges > 0 and ("octave" in here.how.get("step_az", "")) == (
        case == "octave"
    )
    assert here == given
