"""Returns of one scan position checked against what another position sees.

Several scan positions in one tile see the same surfaces from different places.

- Confirmed: a marked return p of position A that position B sees on a surface is no
  blend. B's four beams surrounding p's direction answered from one smooth surface
  (their twist in inverse range, v00 + v11 − v10 − v01, zero on a plane, within the
  scatter) none of them marked mixed, and that surface, interpolated bilinearly in
  inverse range (linear in the angle across a plane seen from the sensor) to p's
  direction, passes within ``sigmas`` × the combined range scatter of p's range
  from B. Such returns lose their marks.
- Free space: an unmarked return p of A lies where B's beams pass to farther
  returns: B's nine beams around p's direction all answered more than ``free_margin``
  beyond p, none of them marked, and B's footprint there is no wider than A's (a
  surface A resolves, B resolves too). Such a return is a blend, if A does not see it
  on a smooth surface of its own (its neighbours along both axes continue through it):
  a wall B sees edge-on or a pole thinner than B's beam leaves B's beams free around a
  correct return of A too, and those lie on smooth surfaces in A's own grid.

Where B does not see p (occluded, outside its field of view) nothing is said. All
array arithmetic on the returns sorted by grid index; the only loop runs over pairs
of positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from terrasift.workers.mixed_grid import grid_index


@dataclass(frozen=True)
class PositionGrid:
    """One scan position's angular grid: steps (radians), range scatter (m), footprint
    (steps)."""

    step_az: float
    step_el: float
    sigma: float
    footprint: float = 1.0


@dataclass(frozen=True)
class _Image:
    """A position's returns as a sparse range image: sorted grid keys with inverse range,
    marks and the index of each return."""

    centre: float  # azimuth the angles are taken about (radians)
    ph_a: float
    ph_e: float
    a0: int
    e0: int
    cols: int
    width: int
    key: NDArray[np.int64]
    inv: NDArray[np.float64]
    marked: NDArray[np.bool_]
    own_key: NDArray[np.int64]  # grid key of each of the position's returns (-1: off grid)

    def at(self, want: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Inverse range (NaN where no return) and mark at each wanted key."""
        j = np.minimum(np.searchsorted(self.key, want), self.key.size - 1)
        hit = (self.key[j] == want) & (want >= 0)
        return np.where(hit, self.inv[j], np.nan), hit & self.marked[j]


def _angles(v: NDArray[np.float64], centre: float) -> tuple[NDArray, NDArray, NDArray]:
    r = np.linalg.norm(v, axis=1)
    az = (np.arctan2(v[:, 1], v[:, 0]) - centre + np.pi) % (2 * np.pi) - np.pi
    el = np.arcsin(np.clip(v[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0))
    return az, el, r


def _image(rel: NDArray[np.float64], g: PositionGrid, marked: NDArray[np.bool_]) -> _Image | None:
    mean = rel[:, :2].mean(axis=0)
    centre = float(np.arctan2(mean[1], mean[0]))
    az, el, r = _angles(rel, centre)
    ia, ok_a = grid_index(az, g.step_az)
    ie, ok_e = grid_index(el, g.step_el)
    ok = ok_a & ok_e & (r > 1e-6)
    if np.count_nonzero(ok) < 16:
        return None
    # each index's offset from its angle (the grid's phase), to place other returns
    ph_a = float(np.median(az[ok] - ia[ok] * g.step_az))
    ph_e = float(np.median(el[ok] - ie[ok] * g.step_el))
    a0, e0 = int(ia[ok].min()) - 2, int(ie[ok].min()) - 2
    width = int(ie[ok].max()) - e0 + 3
    cols = int(ia[ok].max()) - a0 + 3
    own = np.where(ok, (ia - a0) * width + (ie - e0), -1)
    order = np.argsort(own[ok], kind="stable")
    return _Image(
        centre,
        ph_a,
        ph_e,
        a0,
        e0,
        cols,
        width,
        own[ok][order],
        1.0 / r[ok][order],
        marked[ok][order],
        own,
    )


def _smooth(img: _Image, rel: NDArray[np.float64], sigma: float) -> NDArray[np.bool_]:
    """Returns on a smooth surface of their own position's grid: the neighbours either
    side along both axes exist and continue through it in inverse range (second
    difference within 6 sd of range scatter)."""
    r = np.linalg.norm(rel, axis=1)
    ok = img.own_key >= 0
    out = np.ones(r.size, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for stride in (img.width, 1):
            lo, _ = img.at(np.where(ok, img.own_key - stride, -1))
            hi, _ = img.at(np.where(ok, img.own_key + stride, -1))
            out &= np.abs(lo + hi - 2.0 / r) * r**2 <= 6.0 * sigma
    return out & ok


def cross_check(
    xyz: NDArray[np.float64],
    ids: NDArray[np.intp],
    origins: NDArray[np.float64],
    grids: list[PositionGrid | None],
    marked: NDArray[np.bool_],
    sigmas: float = 2.0,
    free_margin: float | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(confirmed, free): marked returns another position sees on a surface, and
    unmarked returns in another position's free space (see the module doc; None
    ``free_margin`` leaves free space out). ``ids`` gives each return's position,
    ``grids`` each position's grid (None: the position takes no part)."""
    n = xyz.shape[0]
    confirmed = np.zeros(n, dtype=bool)
    free = np.zeros(n, dtype=bool)
    k = origins.shape[0]
    if k < 2:
        return confirmed, free
    own = [np.flatnonzero(ids == b) for b in range(k)]
    imgs: list[_Image | None] = []
    for b in range(k):
        g = grids[b]
        ok = g is not None and own[b].size >= 16
        imgs.append(_image(xyz[own[b]] - origins[b], g, marked[own[b]]) if ok else None)  # type: ignore[arg-type]
    sig = np.array([g.sigma if g is not None else np.nan for g in grids])
    fp_m = np.array(
        [g.footprint * max(g.step_az, g.step_el) if g is not None else np.nan for g in grids]
    )
    smooth = np.zeros(n, dtype=bool)
    if free_margin is not None:
        for a in range(k):
            img, g = imgs[a], grids[a]
            if img is not None and g is not None:
                smooth[own[a]] = _smooth(img, xyz[own[a]] - origins[a], g.sigma)
    r_own = np.linalg.norm(xyz - origins[ids], axis=1)
    for b in range(k):
        img, g = imgs[b], grids[b]
        if img is None or g is None:
            continue
        want = (ids != b) & np.isfinite(sig[ids])
        if free_margin is None:
            want &= marked
        others = np.flatnonzero(want)
        if others.size == 0:
            continue
        az, el, d = _angles(xyz[others] - origins[b], img.centre)
        fa = (az - img.ph_a) / g.step_az - img.a0
        fe = (el - img.ph_e) / g.step_el - img.e0
        la, le = np.floor(fa).astype(np.int64), np.floor(fe).astype(np.int64)
        inside = (la >= 1) & (la + 2 < img.cols) & (le >= 1) & (le + 2 < img.width)
        inside &= d > 1e-6
        others, d, fa, fe = others[inside], d[inside], fa[inside], fe[inside]
        la, le = la[inside], le[inside]
        ua, ue = fa - la, fe - le
        tol = sigmas * np.sqrt(g.sigma**2 + sig[ids[others]] ** 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            # confirmed: four beams around p's direction on one unmarked plane through p
            base = la * img.width + le
            got = [img.at(base + da * img.width + de) for da in (0, 1) for de in (0, 1)]
            v, m = [x[0] for x in got], [x[1] for x in got]
            twist = np.abs(v[0] + v[3] - v[1] - v[2])
            vi = (v[0] * (1 - ua) * (1 - ue) + v[1] * (1 - ua) * ue) + (
                v[2] * ua * (1 - ue) + v[3] * ua * ue
            )
            # inverse-range differences to ranges: Δr ≈ Δv × d²; the twist of four
            # beams on a plane scatters by 2 sd of one return: within 3 of those
            on = (np.abs(1.0 / vi - d) <= tol) & (twist * d**2 <= 6.0 * g.sigma)
            on &= ~(m[0] | m[1] | m[2] | m[3]) & marked[others]
            confirmed[others[on]] = True
            if free_margin is None:
                continue
            # free space: B's nine beams around p's direction answer beyond it
            near = np.round(fa).astype(np.int64) * img.width + np.round(fe).astype(np.int64)
            beyond = np.ones(others.size, dtype=bool)
            seen = np.zeros(others.size, dtype=np.int64)
            for da in (-1, 0, 1):
                for de in (-1, 0, 1):
                    vv, mm = img.at(near + da * img.width + de)
                    has = np.isfinite(vv)
                    if da == 0 and de == 0:
                        beyond &= has
                    seen += has
                    beyond &= ~mm & (~has | (1.0 / vv > d + free_margin))
            finer = fp_m[b] * d <= fp_m[ids[others]] * r_own[others]
            hit = beyond & (seen >= 6) & finer & ~marked[others] & ~smooth[others]
            free[others[hit]] = True
    return confirmed, free
