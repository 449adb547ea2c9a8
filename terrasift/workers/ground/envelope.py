"""A local ground plane that low vegetation cannot lift, and the isolated-shrub test.

Where scrub holds a sixth to a third of a point's nearest ground-labelled
neighbours, a least-squares plane through them stands decimetres above the
ground, and clipping the highest residuals by their own deviation does not
bring it down: that deviation is the vegetation's. This plane starts from the
lower envelope instead: the neighbours are split into ``sectors`` equal angular
sectors around the point, and the plane is fitted through the lowest of each
(residuals about a first least-squares plane, so that a slope is not taken for
low ground downhill). Vegetation only stands above the ground, so these lie on
it wherever a sector holds one ground return. The plane then climbs back to the
middle of the ground's noise: it is refitted ``rounds`` times to the neighbours
within ``clip`` deviations above it, the deviation taken from those below it
and never under ``least`` metres (a handful of sector minima give almost none).

The isolated-shrub test (``surrounded``): a compact cluster of returns stands
above a surface that continues under it, so in every angular sector around such
a return one of its nearest neighbours lies lower by at least half the
return's height above the plane. A crest, an embankment's edge or a terrace
is not surrounded: along its length the nearest neighbours stand as high.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def _solve(a: NDArray, z: NDArray, w: NDArray) -> NDArray[np.float64]:
    """Weighted least-squares planes, one per row: (m, k, 3) design, (m, k) z and weights."""
    ata = np.einsum("mk,mki,mkj->mij", w, a, a) + 1e-9 * np.eye(3)
    atz = np.einsum("mk,mki,mk->mi", w, a, z)
    return np.linalg.solve(ata, atz[..., None])[..., 0]


def _sector(d: NDArray[np.float64], sectors: int) -> NDArray[np.int64]:
    """Angular sector (0 … ``sectors`` − 1) of each offset ``d`` (…, ≥ 2)."""
    ang = np.arctan2(d[..., 1], d[..., 0])
    return np.minimum(((ang + np.pi) * (sectors / (2 * np.pi))).astype(np.int64), sectors - 1)


def envelope_plane(
    centre: NDArray[np.float64],
    near: NDArray[np.float64],
    clip: float,
    least: float,
    sectors: int = 8,
    rounds: int = 4,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per row (module doc): height of ``centre`` (m, 3) above the plane of its
    neighbours ``near`` (m, k, 3) started from their lower envelope; the
    neighbours' deviation below it; their residuals about it (m, k); their
    offsets from the centre (m, k, 3)."""
    d = near - centre[:, None, :]
    m, k = d.shape[:2]
    a = np.stack([np.ones((m, k)), d[..., 0], d[..., 1]], axis=-1)
    z = d[..., 2]
    coef = _solve(a, z, np.ones((m, k)))
    res = z - np.einsum("mki,mi->mk", a, coef)
    # The lowest residual of each sector (empty sectors add none).
    sec = _sector(d, sectors)
    rows = np.arange(m)
    w = np.zeros((m, k))
    for s in range(sectors):
        rs = np.where(sec == s, res, np.inf)
        j = np.argmin(rs, axis=1)
        ok = np.isfinite(rs[rows, j])
        w[rows[ok], j[ok]] = 1.0
    coef = _solve(a, z, w)
    res = z - np.einsum("mki,mi->mk", a, coef)
    for _ in range(rounds):
        below = (res < 0) & (w > 0)
        dev = np.sqrt(np.sum(np.where(below, res * res, 0.0), 1) / np.maximum(below.sum(1), 1))
        w = (res <= clip * np.maximum(dev, least)[:, None]).astype(np.float64)
        coef = _solve(a, z, w)
        res = z - np.einsum("mki,mi->mk", a, coef)
    below = (res < 0) & (w > 0)
    dev = np.sqrt(np.sum(np.where(below, res * res, 0.0), 1) / np.maximum(below.sum(1), 1))
    return -coef[:, 0], dev, res, d


def surrounded(
    height: NDArray[np.float64],
    res: NDArray[np.float64],
    d: NDArray[np.float64],
    sectors: int,
    nearest: int,
) -> NDArray[np.bool_]:
    """Per row: in every one of ``sectors`` angular sectors, one of the ``nearest``
    neighbours of that sector (``res``, ``d`` ordered by distance) lies under half
    the centre's ``height`` above the plane (an empty sector: not surrounded)."""
    sec = _sector(d, sectors)
    under = res < 0.5 * height[:, None]
    ok = np.ones(height.shape[0], dtype=bool)
    for s in range(sectors):
        inside = sec == s
        first = inside & (np.cumsum(inside, axis=1) <= nearest)
        ok &= np.any(first & under, axis=1)
    return ok
