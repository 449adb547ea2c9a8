"""Returns of one scan position checked against the surfaces another position sees.

Several scan positions in one tile see the same surfaces from different places. A
return p of position A that position B sees on a surface is no blend: B's beams
around p's direction (the four beams of B's grid surrounding it) answered from one
smooth surface none of them marked mixed, and that surface, interpolated to p's
direction, passes within ``sigmas`` × the combined range scatter of p's range from B.
Such returns are taken off the marks. The test only ever confirms: where B does not
see p (occluded, outside its field of view, past an edge from B's side, a surface
thinner than B's beam) it says nothing. A test the other way (B's beams pass through
p's place to farther returns, so p lies in free space) finds blends but also marks
correct returns on surfaces B sees edge-on or on poles thinner than B's beam; it is
not used.

Inverse range is linear in the angle across a plane seen from the sensor, so the
four beams are interpolated bilinearly in inverse range, and their twist
(v00 + v11 − v10 − v01, zero on a plane) must stay within the same scatter.
Everything is array arithmetic; the only loop runs over pairs of positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from terrasift.workers.mixed_grid import grid_index


@dataclass(frozen=True)
class PositionGrid:
    """One scan position's angular grid: steps (radians) and its range scatter (m)."""

    step_az: float
    step_el: float
    sigma: float


def _angles(v: NDArray[np.float64], centre: float) -> tuple[NDArray, NDArray, NDArray]:
    r = np.linalg.norm(v, axis=1)
    az = (np.arctan2(v[:, 1], v[:, 0]) - centre + np.pi) % (2 * np.pi) - np.pi
    el = np.arcsin(np.clip(v[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0))
    return az, el, r


def _at(
    key: NDArray[np.int64], val: NDArray[np.float64], want: NDArray[np.int64]
) -> NDArray[np.float64]:
    """``val`` at each wanted key of the sorted ``key`` (NaN where none)."""
    j = np.minimum(np.searchsorted(key, want), key.size - 1)
    return np.where(key[j] == want, val[j], np.nan)


def confirmed_elsewhere(
    xyz: NDArray[np.float64],
    ids: NDArray[np.intp],
    origins: NDArray[np.float64],
    grids: list[PositionGrid | None],
    marked: NDArray[np.bool_],
    sigmas: float = 2.0,
) -> NDArray[np.bool_]:
    """Returns lying on a surface that another scan position sees (see the module doc).

    ``ids`` gives each return's position, ``grids`` each position's grid (None: the
    position is not used as a witness), ``marked`` the returns already marked mixed
    (never a witness's surface).
    """
    n = xyz.shape[0]
    out = np.zeros(n, dtype=bool)
    k = origins.shape[0]
    if k < 2:
        return out
    for b in range(k):
        g = grids[b]
        own = np.flatnonzero(ids == b)
        if g is None or own.size < 16:
            continue
        rel = xyz[own] - origins[b]
        mean = rel[:, :2].mean(axis=0)
        centre = float(np.arctan2(mean[1], mean[0]))
        az, el, r = _angles(rel, centre)
        ia, ok_a = grid_index(az, g.step_az)
        ie, ok_e = grid_index(el, g.step_el)
        ok = ok_a & ok_e & ~marked[own] & (r > 1e-6)
        if np.count_nonzero(ok) < 16:
            continue
        # each index's offset from its angle (the grid's phase), to place other returns
        ph_a = float(np.median(az[ok] - ia[ok] * g.step_az))
        ph_e = float(np.median(el[ok] - ie[ok] * g.step_el))
        a0, e0 = int(ia[ok].min()) - 1, int(ie[ok].min()) - 1
        width = int(ie[ok].max()) - e0 + 2
        cols = int(ia[ok].max()) - a0 + 2
        key = (ia[ok] - a0) * width + (ie[ok] - e0)
        order = np.argsort(key, kind="stable")
        key_s, inv_s = key[order], 1.0 / r[ok][order]

        others = np.flatnonzero((ids != b) & marked)
        if others.size == 0:
            continue
        oaz, oel, d = _angles(xyz[others] - origins[b], centre)
        fa = (oaz - ph_a) / g.step_az - a0
        fe = (oel - ph_e) / g.step_el - e0
        la, le = np.floor(fa).astype(np.int64), np.floor(fe).astype(np.int64)
        inside = (la >= 0) & (la + 1 < cols) & (le >= 0) & (le + 1 < width) & (d > 1e-6)
        if not inside.any():
            continue
        others, d, la, le = others[inside], d[inside], la[inside], le[inside]
        ua, ue = fa[inside] - la, fe[inside] - le

        base = la * width + le
        v00, v10 = _at(key_s, inv_s, base), _at(key_s, inv_s, base + width)
        v01, v11 = _at(key_s, inv_s, base + 1), _at(key_s, inv_s, base + width + 1)
        v = v00 * (1 - ua) * (1 - ue) + v10 * ua * (1 - ue) + v01 * (1 - ua) * ue + v11 * ua * ue
        twist = np.abs(v00 + v11 - v10 - v01)
        sa = np.array([gg.sigma if gg is not None else np.nan for gg in grids])[ids[others]]
        tol = sigmas * np.sqrt(g.sigma**2 + np.nan_to_num(sa, nan=g.sigma) ** 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            # inverse-range differences to ranges: Δr ≈ Δv × d²; the twist of four
            # beams on a plane scatters by 2 sd of one return: within 3 of those
            on = (np.abs(1.0 / v - d) <= tol) & (twist * d**2 <= 6.0 * g.sigma)
        out[others[on]] = True
    return out
