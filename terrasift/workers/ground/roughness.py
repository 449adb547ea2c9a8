"""Low vegetation in a ground filter's band, told apart by the ground's own roughness.

On sparse data (a couple of points per final bin) a filter's ground band is
decimetres wide: the surface between nodes metres apart departs from real
terrain by that much on slopes and breaks. Returns from shrubs, hedges and
scrub 0.25–1 m above the ground then pass as ground. Their heights above the
ground are small, but not small against the ground's own roughness: bare
ground, fitted by a plane over a few tens of its neighbours, deviates by its
range noise and curvature (on the synthetic rural slopes the 99th percentile
of bare-ground residuals about a plane through the 8 nearest true ground
points is 0.07–0.26 m), a shrub return stands tens of centimetres
above that plane.

Per labelled ground point, a plane is fitted to its ``k`` nearest labelled
ground neighbours (x, y; the point itself left out) and refitted without the
neighbours more than ``clip`` robust deviations above it (other shrub returns
among them), the deviation taken from the residuals below the plane (ground
noise is two-sided, vegetation stands only above; ``lowveg.local_plane``).
The point is not ground when it stands above that plane by more than
``factor`` times that deviation, or times the median deviation of its
neighbours where that is larger (the ground's own roughness there: range
noise, LAS quantisation, ploughed or rocky ground; taken locally so that a
block labels as the whole tile does), and at least ``floor``. Both the radius (k
neighbours cover k / density m²) and the threshold (the local deviation) are
the data's own; on a crest or an embankment's edge the neighbours fall away on
both sides, their deviation about the plane grows with the curvature, and so
does the threshold.

With ``envelope`` the plane is started from the neighbours' lower envelope
(``envelope.py``), so scrub among them does not lift it; with ``shrub`` > 0 a
point is also taken back when it stands more than ``shrub`` metres above that
plane and is surrounded by lower neighbours (the isolated-shrub test of
``envelope.py``), however rough the ground around it: the test that holds near
an embankment's edge, where the deviation threshold grows with the break.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.workers.ground.envelope import envelope_plane, surrounded
from terrasift.workers.ground.lowveg import local_plane


def rough_points(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    k: int,
    factor: float,
    clip: float,
    floor: float,
    chunk: int = 20_000,
    envelope: bool = False,
    shrub: float = 0.0,
    sectors: int = 4,
    nearest: int = 3,
) -> NDArray[np.bool_]:
    """The points of ``ground`` that stand above the plane of their ``k`` nearest ground
    neighbours by more than ``max(floor, factor × max(deviation, neighbours' median
    deviation))``, or (``shrub`` > 0) by more than ``shrub`` metres where lower
    neighbours surround them in ``sectors`` sectors among their ``nearest`` there
    (module doc; ``envelope``: the plane started from the lower envelope)."""
    ground = np.asarray(ground, dtype=bool)
    out = np.zeros(ground.shape[0], dtype=bool)
    g = np.flatnonzero(ground)
    if k <= 0 or g.size <= k:
        return out
    pts = np.take(xyz, g, axis=0)
    tree = cKDTree(pts[:, :2])
    height = np.empty(g.size)
    dev = np.empty(g.size)
    near = np.empty((g.size, k), dtype=np.int64)
    ring = np.zeros(g.size, dtype=bool)
    lift = np.zeros(g.size)
    low_dev = np.zeros(g.size)
    for a in range(0, g.size, chunk):
        b = min(a + chunk, g.size)
        _, nb = tree.query(pts[a:b, :2], k=k + 1)
        # Column 0 is the point itself (distance 0), unless another point shares
        # its x, y; then one of the two is left out, which changes little.
        near[a:b] = nb[:, 1:]
        if envelope or shrub > 0:
            # The band's least deviation: half the floor (a few sector minima give none).
            h, dv, res, d = envelope_plane(pts[a:b], pts[nb[:, 1:]], clip, 0.5 * floor)
            if shrub > 0:
                ring[a:b] = surrounded(h, res, d, sectors, nearest)
                lift[a:b], low_dev[a:b] = h, dv
        if envelope:
            height[a:b], dev[a:b] = h, dv
        else:
            height[a:b], dev[a:b], _ = local_plane(pts[a:b], pts[nb[:, 1:]], clip)
    # The ground's own roughness around each point: no point is held to less than the
    # median deviation of its neighbours (local, so a block and the whole tile agree).
    around = np.median(dev[near], axis=1)
    scale = np.maximum(dev, around)
    high = height > np.maximum(floor, factor * scale)
    if shrub > 0:
        # Held to the roughness of the ground around the point (its neighbours' deviations
        # below their envelope planes, which scrub does not widen), not to its own
        # deviation, which a break among its neighbours inflates.
        rough = np.median(low_dev[near], axis=1)
        high |= ring & (lift > np.maximum(shrub, factor * rough))
    out[g[high]] = True
    return out
