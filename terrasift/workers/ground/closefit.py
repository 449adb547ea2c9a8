"""Low single returns over the ground surface fitted close around each point.

What the roughness and half-disc tests leave on sparse rural tiles (0.2–1 points
per m²) is single returns 0.25–0.6 m above the ground: no echo marks them, and their
neighbours' planes and wider quadratics deviate by as much as they stand. Only the
ground known to a few centimetres from about a dozen neighbours parts them. Here the
ground is estimated from the *sure* ground (what the tests before left) in
``rounds``: each ground point's height above the quadratic of its ``k`` nearest sure
points (itself left out; refitted without the neighbours high above the first fit),
and the tile's ground noise, the robust deviation (1.4826 x the median absolute
deviation) of the sure points' heights. A point within ``max(floor, factor x noise)``
(after the first round, fitted on ground still holding vegetation: twice that) is sure
in the next round, so each round's surface is fitted on cleaner ground. The last
round's threshold takes instead the noise around the point: the same deviation over the
sure points within ``NOISE_WINDOW`` metres of its ``NOISE_CELL`` grid cell (the tile's
where a window holds too few), a fixed metric neighbourhood, so a job cut into blocks
gives a core point the threshold the whole tile would (the tile's noise differs from
block to block by up to 40 %). With
``clip_noise`` the refits after the first round leave out the neighbours more than
``CLIP`` x min(their fit's deviation, ``clip_noise`` x the first round's noise) above
it: beside low scrub a third of a dozen sure neighbours can be returns 0.15–0.3 m up,
which widen the deviation enough to stay in the refit and lift the surface.

A point goes when, in the last round, it stands above that surface by more than
``max(floor, factor x noise around it)`` and all of:

- more than ``local`` x the robust deviation of the heights of its ``around``
  nearest sure points: where real ground bends within metres (its own neighbours
  stand off their surfaces too) it is held to that;
- at most ``ceiling`` above it: where a dozen points' quadratic overshoots (steep
  breaks, one-sided neighbours) it stands metres off, and vegetation that high was
  taken by the tests before;
- more than ``step`` above the highest of its three nearest sure points: a return
  over the ground between them, where ground on a bump stands level with its nearest;
  with ``step_plane`` those points' heights are first carried to the point along the
  plane of its ``k`` nearest sure points: on a 15–40 % slope at 1–2 m spacing the uphill
  one stands 0.15–0.8 m higher, and the raw step would hide a 0.3 m return beside it;
  with ``step_slope`` > 0 they are carried only where that plane's gradient is at most
  ``step_slope`` x the tile's median gradient (of the same planes over all its ground):
  on a tile-wide slope it is carried, on a crest, dike or bank flank steeper than the
  tile it is not, because there the plane overshoots the ground beside the point;
- above the quadratic of its ``wide`` nearest sure points by more than
  ``wide_factor`` x that surface's deviation (the half-disc test's wider surface).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

CLIP = 2.0  # deviations above the first fit beyond which a neighbour is left out of the refit
MAD_SIGMA = 1.4826  # median absolute deviation to a normal standard deviation
#: metres: the ground noise is taken per cell of this grid (fixed in map coordinates),
#: a third of the window so neighbouring cells' windows share most of their points.
NOISE_CELL = 5.0
#: metres: radius of a cell's noise window around its centre. It holds >= 100 sure points
#: at the sparsest seen density (0.15 pts/m², 707 m²), so the MAD is within ~12 % (1.17 /
#: sqrt(n)); with half the cell's diagonal (3.5 m) and the 12-point fits' reach (<= 5 m at
#: that density) it stays inside the smallest block halo the NIST method asks for (4
#: first-pass cells of >= 6 m = 24 m).
NOISE_WINDOW = 15.0
#: sure points below which a window falls back to the tile's noise (MAD within ~21 %).
NOISE_MIN = 30


def close_fit_high(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    k: int = 12,
    rounds: int = 3,
    floor: float = 0.15,
    factor: float = 3.0,
    ceiling: float = 0.8,
    local: float = 6.0,
    around: int = 24,
    step: float = 0.1,
    wide: int = 30,
    wide_factor: float = 2.5,
    step_plane: bool = False,
    clip_noise: float = 0.0,
    step_slope: float = 0.0,
) -> NDArray[np.bool_]:
    """The points of ``ground`` standing above the quadratic of their ``k`` nearest
    sure ground points beyond the tile's ground noise and the tests of the module doc."""
    ground = np.asarray(ground, dtype=bool)
    out = np.zeros(ground.shape[0], dtype=bool)
    g = np.flatnonzero(ground)
    if g.size <= max(k, around, wide) + 1:
        return out
    sure = ground.copy()
    last: tuple[NDArray, NDArray, NDArray] | None = None
    cap = np.inf
    for r in range(rounds):
        s = np.flatnonzero(sure)
        if s.size <= max(k, around, wide) + 1:
            return out
        tree = cKDTree(xyz[s, :2])
        pos = np.full(ground.shape[0], -1)
        pos[s] = np.arange(s.size)
        # A point whose neighbours are last round's, in the same order, keeps its fit.
        h, dev, rows = _quad_heights(xyz, g, s, tree, pos, k, floor, last, cap)
        last = (h, dev, rows)
        hs = h[sure[g]]
        noise = MAD_SIGMA * float(np.median(np.abs(hs - np.median(hs))))
        if r == 0 and clip_noise > 0:
            # Later fits clip at the first round's noise: their fits differ from this one's.
            cap, last = clip_noise * max(noise, 0.25 * floor), None
        if r < rounds - 1:
            # The first surface is fitted on ground still holding vegetation: it keeps twice as much.
            sure = ground.copy()
            sure[g] = h <= max(floor, (2.0 if r == 0 else 1.0) * factor * noise)
    # The last threshold takes the noise around each point, not the tile's or block's.
    # Only points above the floor and under the ceiling can go: the noise is taken for them.
    flag = (h > floor) & (h <= ceiling)
    flag[flag] = h[flag] > factor * _window_noise(xyz, g, h, sure[g], flag)
    i = np.flatnonzero(flag)
    if i.size == 0:
        return out
    at = np.zeros(ground.shape[0])
    at[g] = h
    nb = _neighbours(xyz, g[i], tree, pos, max(around, 3))
    spread = MAD_SIGMA * np.median(np.abs(at[s[nb[:, :around]]]), axis=1)
    keep = h[i] > local * spread
    near = xyz[s[nb[:, :3]], 2]
    if step_plane:
        near = near + _carried(xyz, g[i], s[nb[:, :k]])[:, :3]
    elif step_slope > 0:
        coef = _plane(xyz, g[i], s[nb[:, :k]])
        tile = float(np.median(np.hypot(*_plane(xyz, g, rows)[:, 1:].T)))
        on = np.hypot(coef[:, 1], coef[:, 2]) <= step_slope * tile
        near = near + np.where(on[:, None], _carried(xyz, g[i], s[nb[:, :3]], coef), 0.0)
    keep &= xyz[g[i], 2] - np.max(near, axis=1) > step
    hw, dw, _ = _quad_heights(xyz, g[i], s, tree, pos, wide, floor)
    keep &= hw > wide_factor * dw
    out[g[i[keep]]] = True
    return out


def _window_noise(
    xyz: NDArray[np.float64],
    g: NDArray[np.int64],
    h: NDArray[np.float64],
    sure: NDArray[np.bool_],
    at: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """Per point of ``g[at]``, the ground noise (1.4826 x MAD of ``h`` over the ``sure`` ones)
    within ``NOISE_WINDOW`` metres of the centre of its ``NOISE_CELL`` grid cell (cells
    fixed in map coordinates), or the tile's where a window holds fewer than
    ``NOISE_MIN`` sure points: the same for a point however the job is cut."""
    if not at.any():
        return np.zeros(0)
    hs, xy = h[sure], xyz[g[sure], :2]
    tile = MAD_SIGMA * float(np.median(np.abs(hs - np.median(hs))))
    cell = np.floor(xyz[g[at], :2] / NOISE_CELL).astype(np.int64)
    uniq, inv = np.unique(cell, axis=0, return_inverse=True)
    lists = cKDTree(xy).query_ball_point((uniq + 0.5) * NOISE_CELL, r=NOISE_WINDOW)
    lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    owner = np.repeat(np.arange(len(lists)), lens)
    flat = hs[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])]
    med = _ragged_median(flat, owner, lens)
    mad = _ragged_median(np.abs(flat - med[owner]), owner, lens)
    noise = np.where(lens >= NOISE_MIN, MAD_SIGMA * mad, tile)
    return np.asarray(noise[np.ravel(inv)], dtype=np.float64)


def _ragged_median(
    v: NDArray[np.float64], owner: NDArray[np.int64], lens: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Median of ``v`` per group (``owner``: group of each value, sorted; ``lens``: sizes)."""
    if v.size == 0:
        return np.zeros(lens.size)
    # One float key (group, then value scaled into [0, 0.5]): argsort is 3x a lexsort.
    span = float(np.ptp(v)) or 1.0
    v = v[np.argsort(owner + 0.5 * (v - v.min()) / span)]
    start = np.concatenate([[0], np.cumsum(lens)[:-1]])
    safe = np.maximum(lens, 1)
    last = v.size - 1
    lo = v[np.minimum(start + (safe - 1) // 2, last)]
    hi = v[np.minimum(start + safe // 2, last)]
    return np.asarray(0.5 * (lo + hi), dtype=np.float64)


def _plane(
    xyz: NDArray[np.float64], idx: NDArray[np.int64], rows: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Per point of ``idx``, the least-squares plane (offset, x and y gradient, centred
    on the point) of its neighbours ``rows`` (point ids)."""
    d = xyz[rows, :2] - xyz[idx, None, :2]
    a = np.concatenate([np.ones(d.shape[:2] + (1,)), d], axis=-1)
    z = xyz[rows, 2]
    at = np.swapaxes(a, 1, 2)
    return np.asarray(np.linalg.solve(at @ a + 1e-9 * np.eye(3), (at @ z[..., None]))[..., 0])


def _carried(
    xyz: NDArray[np.float64],
    idx: NDArray[np.int64],
    rows: NDArray[np.int64],
    coef: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Per point of ``idx``, the rise from each of its neighbours ``rows`` (point ids)
    to the point along the least-squares plane of those neighbours (or ``coef``)."""
    d = xyz[rows, :2] - xyz[idx, None, :2]
    if coef is None:
        coef = _plane(xyz, idx, rows)
    return -(d[..., 0] * coef[:, 1:2] + d[..., 1] * coef[:, 2:3])


def _neighbours(
    xyz: NDArray[np.float64], idx: NDArray[np.int64], tree: cKDTree, pos: NDArray, k: int
) -> NDArray[np.int64]:
    """Positions in the tree of the ``k`` nearest sure points of ``idx`` (itself left out)."""
    _, nb = tree.query(xyz[idx, :2], k=k + 1)
    own = nb[:, 0] == pos[idx]
    return np.where(own[:, None], nb[:, 1:], nb[:, :-1])


def _quad_heights(
    xyz: NDArray[np.float64],
    idx: NDArray[np.int64],
    s: NDArray[np.int64],
    tree: cKDTree,
    pos: NDArray,
    k: int,
    floor: float,
    last: tuple[NDArray, NDArray, NDArray] | None = None,
    cap: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Height of each point of ``idx`` above the quadratic of its ``k`` nearest sure
    points ``s``, refitted once without those more than ``CLIP`` deviations above the
    first fit, that fit's deviation, and the neighbours (point ids, nearest first).
    ``last``: an earlier call's answers for the same ``idx`` and ``k``; rows with the
    same neighbours in the same order take its fits (each row's fit is computed
    alone, so it is the same number)."""
    rows = s[_neighbours(xyz, idx, tree, pos, k)]
    if last is None:
        h, dev = _fit(xyz, idx, rows, floor, cap)
        return h, dev, rows
    new = ~np.all(rows == last[2], axis=1)
    h, dev = last[0].copy(), last[1].copy()
    if new.any():
        h[new], dev[new] = _fit(xyz, idx[new], rows[new], floor, cap)
    return h, dev, rows


def _fit(
    xyz: NDArray[np.float64],
    idx: NDArray[np.int64],
    rows: NDArray[np.int64],
    floor: float,
    cap: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``_quad_heights``' fit of each point of ``idx`` on its neighbours ``rows``
    (the refit leaves out those more than ``CLIP`` x min(deviation, ``cap``) above)."""
    d = xyz[rows] - xyz[idx][:, None, :]
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)
    w = np.ones(z.shape)
    for _ in range(2):
        at = np.swapaxes(a * w[..., None], 1, 2)
        coef = np.linalg.solve(at @ a + 1e-6 * np.eye(6), at @ z[..., None])[..., 0]
        res = z - np.einsum("mkp,mp->mk", a, coef)
        dev = np.sqrt(np.sum(w * res * res, axis=1) / np.maximum(np.sum(w, axis=1) - 6, 1))
        scale = np.minimum(np.maximum(dev, 0.25 * floor), cap)
        w = (res <= CLIP * scale[:, None]).astype(np.float64)
    return np.asarray(-coef[:, 0], dtype=np.float64), np.asarray(dev, dtype=np.float64)
