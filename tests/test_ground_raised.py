"""Raised segments of a ground TIN: the rise rule judges an edge along its own direction."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay

from terrasift.workers.ground import nist
from terrasift.workers.ground.raised import raised_segments


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
    xyz: NDArray[np.float64], along: bool = True, graded: float = 0.0
) -> NDArray[np.bool_]:
    p = nist.NistParams(raised_along=along, raised_graded=graded)
    return raised_segments(
        xyz,
        Delaunay(xyz[:, :2]),
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
