"""Raised segments of a ground TIN: the rise rule judges an edge along its own direction."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay

from terrasift.workers.ground import nist
from terrasift.workers.ground.raised import _on_ramp, raised_segments
from terrasift.workers.ground.tin import Tin


def _yard(noise: float, seed: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Ground at a 2 % grade rising to +y, vertices 2 m apart, and a platform 1 m
    high (40 x 10 m) whose uphill neighbours (wagons) left a 25 m hole: the TIN
    joins its uphill edge to the ground by long edges that run downhill onto it."""
    rng = np.random.default_rng(seed)
    g = np.arange(-40.0, 100.0, 2.0)
    x, y = (a.ravel() for a in np.meshgrid(g, np.arange(-40.0, 90.0, 2.0)))
    x = x + rng.uniform(-0.5, 0.5, x.size)
    y = y + rng.uniform(-0.5, 0.5, y.size)
    top = (x > 10) & (x < 50) & (y > 0) & (y < 10)
    hole = (x > 10) & (x < 50) & (y >= 10) & (y < 35)
    keep = ~hole
    x, y, top = x[keep], y[keep], top[keep]
    z = 0.02 * y + 0.004 * x + np.where(top, 1.0, 0.0) + rng.normal(0.0, noise, x.size)
    return np.column_stack([x, y, z]), top


def _dropped(
    xyz: NDArray[np.float64],
    along: bool = True,
    graded: float = 0.0,
    walled: float = 0.0,
    stage_tin: bool = False,
    even: bool = False,
) -> NDArray[np.bool_]:
    """``raised_segments`` with the stage's parameters on ``xyz``'s triangulation
    (``stage_tin``: the stage's own TIN and height lookup, much faster across holes)."""
    p = nist.NistParams(raised_along=along, raised_graded=graded, raised_walled=walled)
    tin = Tin(xyz, origin=np.zeros(2)) if stage_tin else None
    return raised_segments(
        xyz,
        Delaunay(xyz[:, :2]) if tin is None else tin.tri,
        p.raised_step,
        p.raised_slope,
        up_share=p.raised_share,
        min_lift=p.raised_lift,
        relative=p.raised_relative,
        walls=p.raised_walls,
        rise=p.raised_rise,
        rim=p.raised_rim,
        edge=p.raised_edge,
        along=p.raised_along,
        graded=p.raised_graded,
        walled=p.raised_walled,
        even=even,
        heights=None if tin is None else (lambda q: nist._inside(tin, q)),
    )


def test_platform_in_a_hole_is_dropped_whether_coordinates_are_rounded_or_not():
    # The ground falls 0.5 m along the 25 m edges from its foot to the platform:
    # judged by the size of the slope at the foot alone, that fall counted as a
    # rise the terrain predicts, and the platform joined the terrain on some
    # draws of the noise or of a 1 cm rounding and not on others.
    verdicts = []
    for seed in range(6):
        xyz, top = _yard(0.02, seed)
        for pts in (xyz, np.round(xyz, 2)):
            assert np.array_equal(_dropped(pts), top), seed
            verdicts.append(np.array_equal(_dropped(pts, along=False), top))
    assert not all(verdicts)  # the slope's size alone: the verdict depends on the draw


def test_rise_rule_keeps_a_slope_that_a_long_edge_climbs():
    # No platform: long edges across the hole climb the 2 % grade, as the slope
    # at their foot predicts, so nothing is raised.
    xyz, top = _yard(0.02, 0)
    xyz[top, 2] -= 1.0
    assert not _dropped(xyz).any()


def test_platform_level_with_the_ground_across_a_hole_is_dropped():
    # The ground rises 3 % away from a 1.2 m platform: across a 40 m hole its far
    # side stands as high as the platform's top, so the long edges are level. The
    # terrain behind their far end, over as many metres, predicts a fall of 1.2 m
    # onto the platform: its top stands that much above the prediction.
    rng = np.random.default_rng(0)
    x, y = (
        a.ravel() for a in np.meshgrid(np.arange(-40.0, 100.0, 2.0), np.arange(-40.0, 130, 2.0))
    )
    x, y = x + rng.uniform(-0.5, 0.5, x.size), y + rng.uniform(-0.5, 0.5, y.size)
    top = (x > 10) & (x < 50) & (y > 0) & (y < 10)
    keep = ~((x > 10) & (x < 50) & (y >= 10) & (y < 50))
    x, y, top = x[keep], y[keep], top[keep]
    z = 0.03 * y + np.where(top, 1.2, 0.0) + rng.normal(0.0, 0.02, x.size)
    xyz = np.round(np.column_stack([x, y, z]), 2)
    assert np.array_equal(_dropped(xyz), top)
    assert not _dropped(xyz, along=False).any()


def _cut_by_the_edge(sides: float, seed: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Level ground, vertices 1.4 m apart (0.5 pts/m²), and a raised strip 8 m wide
    and 2 m high from the data's south edge (y = -40) to y = 40: an embankment whose
    sides fall at 1:``sides`` (run ``2 * sides`` m, with vertices on them), or with
    ``sides`` 0 a platform behind walls. Also the crest's vertices."""
    rng = np.random.default_rng(seed)
    g = np.arange(-40.0, 100.0, 1.4)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = np.clip(x + rng.uniform(-0.4, 0.4, x.size), -40.0, None)
    y = np.clip(y + rng.uniform(-0.4, 0.4, y.size), -40.0, None)
    d = np.maximum(np.abs(x - 30.0) - 4.0, np.maximum(y - 40.0, 0.0))
    z = 2.0 * (d <= 0) if sides == 0 else np.clip(2.0 - d / sides, 0.0, 2.0)
    z = z + rng.normal(0.0, 0.02, x.size)
    return np.round(np.column_stack([x, y, z]), 2), d <= 0


def test_embankment_cut_by_the_data_edge_is_kept_and_a_platform_is_not():
    # Railway seed 413: a 2 m road embankment reached the tile's edge along its 8 m
    # crest, under ``raised_edge``, and went as a platform would. Its sides carry
    # ground the TIN descends in low steps, falling on beyond each step's foot.
    for seed in range(3):
        xyz, crest = _cut_by_the_edge(1.5, seed)
        assert _dropped(xyz)[crest].mean() > 0.9, seed  # the rule off
        assert not _dropped(xyz, graded=0.5)[crest].any(), seed
        xyz, top = _cut_by_the_edge(0.0, seed)
        assert np.array_equal(_dropped(xyz, graded=0.5), top), seed


def _walled_platform(seed: int, high: float) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A platform ``high`` m above level ground (80 x 8 m, vertices 2 m apart, 1 cm
    coordinates) with a 36 m hole along its south side (its neighbours, wagons, left
    it), and beyond the hole ground rising 4 % toward it: the terrain there bends
    from that grade to level under the hole (railway seed 618)."""
    rng = np.random.default_rng(seed)
    x, y = (
        a.ravel() for a in np.meshgrid(np.arange(-40.0, 140.0, 2.0), np.arange(-80.0, 90.0, 2.0))
    )
    x, y = x + rng.uniform(-0.5, 0.5, x.size), y + rng.uniform(-0.5, 0.5, y.size)
    top = (x > 10) & (x < 90) & (y > 36) & (y < 44)
    keep = ~((x > 10) & (x < 90) & (y >= 0) & (y <= 36))
    x, y, top = x[keep], y[keep], top[keep]
    z = 0.04 * np.minimum(y, 0.0) + np.where(top, high, 0.0) + rng.normal(0.0, 0.02, x.size)
    return np.round(np.column_stack([x, y, z]), 2), top


def test_walled_platform_met_across_a_hole_at_a_gentle_grade_is_dropped():
    # Railway seed 618: the terrain behind the hole's far side, extrapolated over the
    # 36 m edges, predicts the platform's height, so no edge across the hole is a step
    # and they join it to the terrain; its walls on the other sides say it stands 1 m
    # above the ground, and the edges across the hole fall as far.
    for seed in range(3):
        for high in (0.8, 1.0, 1.3):
            xyz, top = _walled_platform(seed, high)
            assert not _dropped(xyz, stage_tin=True).any(), (seed, high)  # the rule off: kept
            on = _dropped(xyz, graded=0.5, walled=0.5, stage_tin=True)
            assert np.array_equal(on, top), (seed, high)
        # No platform, the same ground and hole: nothing is raised.
        xyz, top = _walled_platform(seed, 0.0)
        assert not _dropped(xyz, graded=0.5, walled=0.5, stage_tin=True).any(), seed


def _bending_platform(
    seed: int, high: float, uneven: float = 0.0
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Ground waving 1 m over 150 m along x (vertices 2 m apart, 1 cm coordinates) and a
    platform ``high`` m above it, 130 x 7 m, level across and following the ground along
    its length, walled all round but for a 50 x 8 m hole beside it (wagons' places) that
    the TIN crosses by gentle edges (railway seed 721). ``uneven``: its height above the
    ground varies by that much along it (a hillside cut off, not a platform)."""
    rng = np.random.default_rng(seed)
    x, y = (
        a.ravel() for a in np.meshgrid(np.arange(-40.0, 190.0, 2.0), np.arange(-40.0, 90.0, 2.0))
    )
    x, y = x + rng.uniform(-0.5, 0.5, x.size), y + rng.uniform(-0.5, 0.5, y.size)
    top = (x > 10) & (x < 140) & (y > 20) & (y < 27)
    keep = ~((x > 40) & (x < 90) & (y > 12) & (y <= 20))
    x, y, top = x[keep], y[keep], top[keep]
    lift = high + uneven * np.sin(x / 8.0)
    z = np.sin(2 * np.pi * x / 150.0) + np.where(top, lift, 0.0) + rng.normal(0.0, 0.02, x.size)
    return np.round(np.column_stack([x, y, z]), 2), top


def test_platform_bending_with_the_ground_under_it_is_dropped():
    # Railway seed 721: platforms 110-140 m long follow ground that bends under them, so
    # they leave their least-squares plane by 0.31-0.36 m RMS, more than ``raised_step``;
    # one gentle edge across a hole beside each made the flatness rule keep them. Their
    # walls stand at one height all round.
    rules = {"graded": 0.5, "walled": 0.5, "stage_tin": True}
    for seed in range(2):
        for high in (0.8, 1.2):
            xyz, top = _bending_platform(seed, high)
            assert not _dropped(xyz, **rules).any(), (seed, high)  # the rule off: kept
            assert np.array_equal(_dropped(xyz, even=True, **rules), top), (seed, high)
        # The same patch standing 0.3-1.9 m above the ground: walls of uneven height.
        xyz, top = _bending_platform(seed, 1.1, uneven=0.8)
        assert not _dropped(xyz, even=True, **rules).any(), seed


def test_ramp_counts_match_a_count_per_step_over_near_and_far_steps() -> None:
    # _on_ramp reads the returns through a grid of cells: each step's counts must equal a
    # direct count over every return, for steps sharing cells, steps hundreds of metres
    # apart (wide cells) and a step with no rise.
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(0, 40, (4000, 2)), rng.normal(0, 1, 4000)])
    pts = np.vstack([pts, pts + [900.0, 700.0, 0.0]])
    foot = np.column_stack([rng.uniform(0, 40, (60, 2)), rng.normal(0, 1, 60)])
    foot[30:] += [900.0, 700.0, 0.0]
    top = foot + np.column_stack([rng.normal(0, 3, (60, 2)), rng.normal(0, 1, 60)])
    top[0, 2] = foot[0, 2]
    for both in (False, True):
        got = _on_ramp(pts, foot, top, both=both)
        want_on, want_mid = np.zeros(60), np.zeros(60)
        for j in range(60):
            d = top[j, :2] - foot[j, :2]
            run = max(float(np.hypot(*d)), 1e-9)
            rise = top[j, 2] - foot[j, 2] or 1e-9
            q = pts[np.hypot(*(pts[:, :2] - 0.5 * (foot[j, :2] + top[j, :2])).T) <= 0.5 * run]
            u, v = q[:, 0] - foot[j, 0], q[:, 1] - foot[j, 1]
            t = (u * d[0] + v * d[1]) / run**2
            inside = (t > 0.2) & (t < 0.8) & (np.abs(u * d[1] - v * d[0]) / run < 0.5 * run)
            f = (q[inside, 2] - foot[j, 2]) / rise
            t = t[inside]
            if both:
                want_on[j] = np.sum((f > 0.25) & (f < 0.75))
                want_mid[j] = inside.sum() * ((f <= 0.25).any() and (f >= 0.75).any())
            else:
                want_on[j], want_mid[j] = np.sum(np.abs(f - t) < 0.25), inside.sum()
        assert want_mid.sum() > 100, both  # the steps do read returns
        assert np.array_equal(got[0], want_on), both
        assert np.array_equal(got[1], want_mid), both
