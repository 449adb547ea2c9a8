"""Low vegetation a ground filter took as ground, taken back.

A ground filter accepts what lies within its band of the surface it built
(decimetres, so that rough and sloping ground passes). Returns from the edge
of a bush or from grass 5–50 cm high lie in that band on flat ground. Two
kinds of evidence tell them apart, each the data's own:

1. **Echoes.** A return that is not the last of its pulse let the pulse go
   on: something was behind it. Ground is opaque, so such a return is not
   ground (where the data carry return numbers; both lidR example surveys
   have no provider-classified ground among their 29 154 and 11 570
   non-last returns).
2. **Height above the local ground by more than the ground's own
   roughness.** Per ground point, a plane is fitted to its ``neighbours``
   nearest ground points (x, y), refitted without the neighbours standing
   more than ``clip`` robust deviations above it (the other bush returns
   among them); the point is not ground when it stands above that plane by
   more than ``factor`` times the robust deviation of the neighbours about it
   (and at least ``floor``). The threshold follows the data: a few cm on
   smooth ground with 3 cm range noise, decimetres on rough rock, a scree
   slope or a ploughed field. Inside vegetation that deviation is the
   vegetation's: shrub returns lower than the sensor's dead zone (one return,
   no echo) stand among the ground-labelled neighbours and widen it to
   decimetres (0.2–0.3 m against 0.01–0.05 m on the bare ground of the
   synthetic rural slopes). With ``ground_percentile`` > 0 a point is held to
   the smaller of its own deviation and that percentile of its neighbours'
   deviations: the roughness of the ground beside the vegetation. Off by
   default: on the synthetic rural slopes it takes more of that vegetation,
   but on Topography.laz, the one real survey at hand that carries returns,
   it costs kappa (README *Measured*).

The second test runs only where echoes show vegetation nearby: a non-last
return lies within ``reach`` times the radius of the point's ``neighbours``. A crest, a rim
or an embankment's edge also stands above the plane of its neighbours, and
bare ground has no vegetation echoes around it; data without return numbers
get the echo test of neither (on the ISPRS samples, which have none, the
height test alone cost 0.3–6 points of mean kappa at ``factor`` 6–3, most of
it on the sharp ridge of samp61). Where the fitted plane is steeper than
``max_slope`` a height in z says little (faces, rims); those points are left
as they are.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from terrasift.workers.registry import StageParams, register


class LowVegParams(StageParams):
    """Parameters of the low-vegetation rule after the ground stage."""

    enabled: bool = True
    """Run the rule (false: the filter's labels as they are)."""
    echoes: bool = True
    """Take back ground returns that are not the last of their pulse (where known)."""
    neighbours: int = Field(32, ge=6, le=64)
    """Ground points (nearest in x, y) the local plane is fitted to: enough that
    their spread about the plane holds the ground's curvature as well as its
    noise. The top of a round hill stands above the plane of its neighbours
    by about √3 times their spread from curvature alone, and noise decides
    whether that passes ``factor``. On a 2.5 m hill (4 m sigma, 4 pts/m², a
    tree on its top) 16 neighbours took 10 of its 649 ground points, its top
    among them, and 32 one; the vegetation taken back was 113 and 116
    points."""
    clip: float = Field(2.0, gt=0.0, le=10.0)
    """Robust deviations above the first plane beyond which a neighbour is left
    out of the second fit."""
    factor: float = Field(4.0, gt=0.0, le=20.0)
    """Robust deviations above the plane beyond which a point is vegetation."""
    ground_percentile: float = Field(0.0, ge=0.0, le=100.0)
    """Percentile of the neighbours' deviations a point's own deviation is capped at:
    the ground's roughness beside the vegetation (0, the default: the point's own
    deviation; 25 with ``factor`` 6 was the best tried, README *Measured*)."""
    reach: float = Field(1.0, ge=0.0, le=10.0)
    """The height test runs where a non-last return lies within this many times the
    radius of the point's ``neighbours``."""
    floor: float = Field(0.05, ge=0.0, le=5.0)
    """Metres: the least height above the plane that counts (LAS quantisation
    and a perfectly smooth surface give a deviation of almost nothing)."""
    max_slope: float = Field(45.0, gt=0.0, lt=90.0)
    """Degrees: points whose fitted plane is steeper are left alone."""
    chunk: int = Field(50_000, ge=1000, le=10_000_000)
    """Points fitted at once (memory: chunk × neighbours × 3 doubles)."""


@register(
    "ground.lowveg",
    LowVegParams,
    "low vegetation the ground filter took, taken back: non-last returns, and returns "
    "standing above the local ground plane by more than its roughness",
)
def reject_low_vegetation(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    params: LowVegParams,
    last_return: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """``ground`` less the low vegetation found by the rule of the module doc."""
    ground = np.asarray(ground, dtype=bool).copy()
    if not params.enabled or last_return is None:
        return ground
    last = np.asarray(last_return, dtype=bool)
    if params.echoes:
        ground &= last
    xyz = np.asarray(xyz, dtype=np.float64)
    g = np.flatnonzero(ground)
    k = params.neighbours
    if g.size <= k or last.all():
        return ground
    pts = xyz[g]
    tree = cKDTree(pts[:, :2])
    echoes = cKDTree(xyz[~last, :2])
    tan_max = np.tan(np.radians(params.max_slope))
    # Which points are tested (echoes within reach), and their neighbours.
    tested, near = [], []
    for a in range(0, g.size, params.chunk):
        b = min(a + params.chunk, g.size)
        dist, nb = tree.query(pts[a:b, :2], k=k + 1)
        veg, _ = echoes.query(pts[a:b, :2])
        i = np.flatnonzero(veg <= params.reach * dist[:, -1])
        tested.append(a + i)
        near.append(nb[i, 1:].astype(np.int32))
    t = np.concatenate(tested)
    if t.size == 0:
        return ground
    nb_t = np.concatenate(near)
    # Planes of the tested points and, for the cap, of their neighbours.
    need = np.zeros(g.size, dtype=bool)
    need[t] = True
    if params.ground_percentile > 0:
        need[nb_t.ravel()] = True
    dev = np.full(g.size, np.inf)
    height = np.zeros(g.size)
    grad = np.zeros(g.size)
    todo = np.flatnonzero(need)
    for a in range(0, todo.size, params.chunk):
        i = todo[a : a + params.chunk]
        _, nb = tree.query(pts[i, :2], k=k + 1)
        # The point itself left out of its plane.
        height[i], dev[i], grad[i] = local_plane(pts[i], pts[nb[:, 1:]], params.clip)
    scale = dev[t]
    if params.ground_percentile > 0:
        scale = np.minimum(scale, np.percentile(dev[nb_t], params.ground_percentile, axis=1))
    high = (height[t] > np.maximum(params.floor, params.factor * scale)) & (grad[t] <= tan_max)
    ground[g[t[high]]] = False
    return ground


def local_plane(
    centre: NDArray[np.float64], near: NDArray[np.float64], clip: float, rounds: int = 4
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per row: height of ``centre`` above the plane of its neighbours ``near``
    (m, k, 3); the neighbours' deviation about it; the plane's gradient (rise
    per metre). The plane is refitted ``rounds`` times without the neighbours
    more than ``clip`` deviations above it, the deviation taken from those
    below it (ground noise is two-sided, vegetation stands only above), so
    that it settles on the ground under a bush whose returns are many of
    the neighbours."""
    d = near - centre[:, None, :]
    a = np.stack([np.ones(d.shape[:2]), d[..., 0], d[..., 1]], axis=-1)  # (m, k, 3)
    z = d[..., 2]
    w = np.ones(z.shape)
    ridge = 1e-9 * np.eye(3)
    for _ in range(rounds):
        ata = np.einsum("mk,mki,mkj->mij", w, a, a) + ridge
        atz = np.einsum("mk,mki,mk->mi", w, a, z)
        coef = np.linalg.solve(ata, atz[..., None])[..., 0]
        res = z - np.einsum("mki,mi->mk", a, coef)
        below = (res < 0) & (w > 0)
        dev = np.sqrt(np.sum(np.where(below, res * res, 0.0), axis=1) / np.maximum(below.sum(1), 1))
        w = (res <= clip * np.maximum(dev, 1e-6)[:, None]).astype(np.float64)
    # The plane's height at the centre is coef[:, 0] (relative to the centre's z).
    return -coef[:, 0], dev, np.hypot(coef[:, 1], coef[:, 2])
