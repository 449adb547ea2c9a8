"""Low vegetation near slope breaks: heights over half-disc planes of sure ground.

The roughness test (``roughness.py``) holds a point to a threshold that scales
with the deviation of its few tens of ground neighbours about their plane. Near
an embankment's edge or a cutting those neighbours lie on two facets, their
deviation grows with the break, and shrubs beside the break pass. Here a point
is judged against a few (``k``) of its nearest *sure* ground points (the ground
left after the roughness test) through several planes: the plane of all ``k``,
and the plane of each half-disc (the neighbours on one side of a line through
the point, ``halves`` directions). Near a break one half lies on the point's own
facet, and its plane fits that facet with the ground's own deviation, not the
break's. A plane is *good* when it holds at least ``least`` points and its
deviation is within ``spread`` times the least deviation among the point's
planes plus ``floor`` (planes across a break fit worse and are not used).

A point is vegetation when it stands above every good plane by more than
``max(floor, factor x d)``, d the larger of that plane's deviation and the
ground's roughness around the point (the median of its sure neighbours' best
deviations: a facet's, not a break's). A crest point lies on the
plane of the half on the crest; a point on an embankment's side lies under the
plane of the half on the top; both are kept. A shrub on a flat beside a break
stands above the plane of the flat and is not under any good plane.

Real ground also bends within a few metres (mounds, rounded crests, the shoulders
and toes of field banks): on the ISPRS samples 1–6 % of the ground stands that high
above every plane. With ``curve`` a point must also stand above the quadratic
surface of its ``curve`` nearest sure points, beyond that surface's own deviation:
a quadratic follows a mound or a rounded crest and not a shrub on a flat or beside a
break (it fits across the break badly, its deviation grows and the point is kept).
Over some tens of points (several metres at 0.2–1 pts/m²) the quadratic cannot follow
mounds and waves a few metres across: its deviation grows with them and a low shrub
(0.25–0.6 m) passes under ``curve_factor`` times it. With ``close`` a point the quadratic
kept still goes when it stands above the quadratic of its ``close`` nearest sure points
(a few metres) by more than ``close_factor`` times that surface's deviation: that surface
follows the relief, and the wide factor keeps real bends that fit it badly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.workers.ground._plane_kernels import half_planes

CLIP = 2.0  # deviations above the quadratic beyond which a neighbour is left out of the refit


def half_disc_high(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    sure: NDArray[np.bool_],
    k: int = 12,
    halves: int = 8,
    least: int = 5,
    factor: float = 4.0,
    floor: float = 0.1,
    spread: float = 2.0,
    noise: float = 0.25,
    chunk: int = 20_000,
    curve: int = 0,
    curve_factor: float = 5.0,
    close: int = 0,
    close_factor: float = 10.0,
) -> NDArray[np.bool_]:
    """The points of ``ground`` standing above every good plane of their ``k`` nearest
    ``sure`` points (all ``k``, and each of ``halves`` half-discs) by more than
    ``max(floor, factor x max(deviation, roughness around))`` (module doc); with
    ``curve`` > 6, only those also above the quadratic of their ``curve`` nearest sure
    points by more than ``max(floor, curve_factor x its deviation)``; with ``close`` > 6,
    those also within ``max(floor, close_factor x deviation)`` of the quadratic of their
    ``close`` nearest sure points go too (module doc)."""
    ground = np.asarray(ground, dtype=bool)
    sure = np.asarray(sure, dtype=bool) & ground
    out = np.zeros(ground.shape[0], dtype=bool)
    g, s = np.flatnonzero(ground), np.flatnonzero(sure)
    if s.size <= k + 1:
        return out
    spts = np.take(xyz, s, axis=0)
    tree = cKDTree(spts[:, :2])
    pos = np.full(ground.shape[0], -1)
    pos[s] = np.arange(s.size)
    ang = 2 * np.pi * np.arange(halves) / halves
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (halves, 2)
    planes = halves + 1
    hh = np.zeros((planes, g.size))
    dd = np.zeros((planes, g.size))
    good = np.zeros((planes, g.size), dtype=bool)
    near = np.zeros((g.size, k), dtype=np.int64)
    best = np.full(g.size, np.inf)
    for a in range(0, g.size, chunk):
        i = g[a : a + chunk]
        b = a + i.size
        _, nb = tree.query(xyz[i, :2], k=k + 1)
        # Leave the point itself out when it is sure (then it is its own nearest).
        own = nb[:, 0] == pos[i]
        nb = np.where(own[:, None], nb[:, 1:], nb[:, :-1])
        near[a:b] = nb
        d = spts[nb] - xyz[i][:, None, :]
        hh[:, a:b], dd[:, a:b], nn = half_planes(d, u)
        enough = nn >= least
        best[a:b] = np.min(np.where(enough, dd[:, a:b], np.inf), axis=0)
        good[:, a:b] = enough & (dd[:, a:b] <= spread * np.maximum(best[a:b], noise * floor))
    # The ground's own roughness around each point: the median of its sure neighbours'
    # best-fitting deviations (a facet's, not a break's), so rough ground is held to it.
    at = np.full(ground.shape[0], -1)
    at[g] = np.arange(g.size)
    around = np.median(np.where(np.isfinite(best), best, 0.0)[at[s[near]]], axis=1)
    thr = np.maximum(floor, factor * np.maximum(dd, around))
    above = hh > thr
    judged = np.any(good, axis=0)
    out[g] = judged & np.all(above | ~good, axis=0)
    if curve > 6 and s.size > curve + 1:
        flagged = out.copy()
        out &= ~_under_curve(xyz, np.flatnonzero(out), tree, spts, pos, curve, curve_factor, floor)
        if close > 6 and s.size > close + 1:
            held = flagged & ~out
            under = _under_curve(
                xyz, np.flatnonzero(held), tree, spts, pos, close, close_factor, floor
            )
            out |= held & ~under
    return out


def _under_curve(
    xyz: NDArray[np.float64],
    idx: NDArray[np.int64],
    tree: cKDTree,
    spts: NDArray[np.float64],
    pos: NDArray[np.int64],
    k: int,
    factor: float,
    floor: float,
) -> NDArray[np.bool_]:
    """Mask over ``xyz``: the points ``idx`` within ``max(floor, factor x deviation)`` of
    the quadratic surface of their ``k`` nearest sure points (themselves left out), refitted
    once without the neighbours more than ``CLIP`` deviations above it (a shrub return
    among them bends it up)."""
    out = np.zeros(xyz.shape[0], dtype=bool)
    if idx.size == 0:
        return out
    _, nb = tree.query(xyz[idx, :2], k=k + 1)
    own = nb[:, 0] == pos[idx]
    nb = np.where(own[:, None], nb[:, 1:], nb[:, :-1])
    d = spts[nb] - xyz[idx][:, None, :]
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)
    w = np.ones(z.shape)
    for _ in range(2):  # fitted, then refitted without the neighbours high above it
        at = np.swapaxes(a * w[..., None], 1, 2)
        coef = np.linalg.solve(at @ a + 1e-6 * np.eye(6), at @ z[..., None])[..., 0]
        res = z - np.einsum("mkp,mp->mk", a, coef)
        dev = np.sqrt(np.sum(w * res * res, axis=1) / np.maximum(np.sum(w, axis=1) - 6, 1))
        w = (res <= CLIP * np.maximum(dev, 0.25 * floor)[:, None]).astype(np.float64)
    out[idx] = -coef[:, 0] <= np.maximum(floor, factor * dev)
    return out


def half_disc_vegetation(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    k: int,
    rounds: int,
    factor: float,
    floor: float,
    curve: int = 0,
    curve_factor: float = 5.0,
    close: int = 0,
    close_factor: float = 10.0,
) -> NDArray[np.bool_]:
    """The points of ``ground`` that ``half_disc_high`` finds above the planes of the
    sure ground: ``ground`` cleaned ``rounds`` − 1 times by the same test held to half
    the ``factor`` and ``floor`` (a sure point may be lost, a shrub return among them
    lifts the planes of its neighbours), then every point of ``ground`` judged; ``curve``
    and ``curve_factor`` as in ``half_disc_high`` (halved for the cleaning too); ``close``
    and ``close_factor`` in the final judgement only."""
    ground = np.asarray(ground, dtype=bool)
    sure = ground.copy()
    for _ in range(rounds - 1):
        sure &= ~half_disc_high(
            xyz,
            ground,
            sure,
            k,
            factor=0.5 * factor,
            floor=0.5 * floor,
            curve=curve,
            curve_factor=0.5 * curve_factor,
        )
    return half_disc_high(
        xyz,
        ground,
        sure,
        k,
        factor=factor,
        floor=floor,
        curve=curve,
        curve_factor=curve_factor,
        close=close,
        close_factor=close_factor,
    )
