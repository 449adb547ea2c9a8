"""Mixed measurements found in the scan's own angular grid (a sparse range image).

A ground-based scanner casts its beams on lines of constant azimuth and
elevation steps. With the steps measured from the points (``scan_geometry``),
every return gets its beam's grid index (azimuth column, elevation row) and the
scan becomes a range image. A mixed return blends a foreground and a background
seen in one footprint, so along a scan line it lies *between* them: its range
is farther than a surface on one side and nearer than a surface on the other,
and it lies on neither of them. When the footprint spans several steps the
blend spreads as a ramp of several beams; the surfaces are then looked for up
to ``reach`` beams away on each side.

A return p is mixed along one axis (azimuth or elevation) when on one side an
*anchor* a (a return on a surface: the line through its two outer neighbours
continues through it) lies nearer than p, on the other side an anchor b lies
farther, both within ``max_gap`` of p in range (the anchor or its surface continued
to p's beam), p is off a and b by more than the
margin, the surface of each anchor, extrapolated to p's beam, misses p, and at
most ``span`` beams lie between the anchors (a blend spans about a footprint).
Along azimuth the anchors may lie farther apart when every beam out to each of
them moves one way (farther towards the farther, nearer towards the nearer) by
more than the margin, each off that anchor's surface, and not all on one line
with their neighbours: a surface narrower than the footprint between two others
(a board seen between a nearer board and the wall) shows no anchored return of
its own, so the ramps of its two edges join into one run of blends (``_cascade``).
Surfaces are continued in inverse range, which is linear in the angle along a
plane seen from the sensor (exactly for the ground along elevation, however
grazing), so far grazing ground passes as a surface, not as a ramp. "Misses p"
is judged across the surface too: the change of inverse range per beam along
both axes gives the surface's incidence at p's beam, and a range offset times
cos(incidence) must exceed ``min_offset`` (a blend of grazing ground with a wall's
foot lies 20 cm off the ground in range but 2 cm above it), while the range
offset itself must exceed the margin and the continuation's scatter (range noise
lies along the ray, so across a grazing surface it shrinks as the offset does).

Along elevation a blend of grazing ground with the foot of an object above it (a
board standing clear of the ground, the ground running on under it) lies nearer than
the ground's last beams, like the object: the ground continued to its beam passes
behind it, so the ground counts as the farther surface there (not for a return level
with its azimuth neighbours one and two beams away: a wall's foot row). The front of a thin object one beam
wide is an anchor of its own when both its neighbours lie behind it by more than a
convex surface recedes in one beam (step × range) and neither lies on a surface.
Likewise along azimuth the scan's last beam on a side, behind a ramp that runs out to
it (each beam farther than the one before by more than margin + step × range, the
ramp's returns on no line of two beams) from an anchor nearer than p, is the farther
surface: a background at the field of view's edge shows one beam, no line.
A beam whose next beams outwards are a thin object's run (a wall seen one beam wide
between a pole's blends and a board's ramp) is an anchor when the surface beyond the
run, continued across it, lands on it (``_past_thin_run``).

Thin objects narrower than the footprint leave no correct return at all: along
a line they are a run of at most ``thin`` beams (about two footprints) in front
of one background surface that continues behind them (or, seen one beam on each
side, agrees with itself across the run). Such runs are marked too,
and so are runs in front of a background on one side only, cut on the other by a
surface nearer than any blend reaches (``max_gap``), when they recede into that cut:
the object's far edge then lies within the run (a pole before a wall's end, a board
hiding the wall beyond it).

The dual along azimuth: a surface seen only through a gap narrower than the footprint
between two others (the wall behind a board, between the board's edge and a nearer
wall's edge) shows no return of its own, so a short run of beams on no surface climbs
from one side's surface to a peak beyond both and falls to the other (``_hidden_gaps``);
its returns off both surfaces are marked.

Where nothing answers behind an edge (no return, or a background farther than
``max_gap``), a return that lies off the surface it ends by more than that surface
alone could pull it (its continuation taken back half a footprint of beams), and
within ``max_gap`` of it, blends it with a background that ends within the beam:
marked. Only with ``open_edges``
(off by default: such a return answers from one surface, so it is no blend, only
displaced by the beam's width): a return off the surface it ends (that surface continued to its beam
misses it by more than its scatter and ``min_offset`` across it) is a blend with
nothing: the part of a footprint still on a sloped surface answers at that part's
mean range (nearer than where the central ray meets grazing ground towards the
range limit). Otherwise a beam whose footprint still touches the surface returns its range
on its own ray, up to half a footprint past the edge: those beams are marked
when displaced by more than ``min_offset`` with a probability above ``bleed_prob``
(``_bleeding``; face on the shift is sideways, so range noise does not blur it; along
an oblique surface, seen along azimuth, the part still on the surface answers at its
mean range, so a beam's range says where the edge fell and how far off the surface it
lies). An edge
counts only where the surface, continued to the next beam, would have answered
within ``max_gap``: grazing ground ending at the range limit recedes out of reach
and does not end there.

When the returns carry GPS time, each is placed on the grid by its firing
order instead (``time_index``): the pulse number from its time, the column
length from the angles of the sharp returns, so returns whose angle the LAS
scale blurs beyond a beam (near the sensor) are judged on their own beam too.

Everything is array arithmetic on the points sorted by grid index, the tests of
each anchor in one compiled pass (``_mixed_kernels``); the only Python loops run
over the few beam offsets within reach.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._mixed_kernels import (
    anchor_pass,
    behind_both,
    edge_drops,
    line_gather,
    past_run,
    spread_of,
)

OFF_GRID = 0.35  # a beam's angle lies within this many steps of its grid line


@dataclass(frozen=True)
class GridSettings:
    """Lengths in metres, angles in radians."""

    step_az: float
    step_el: float
    sigma: float  # range scatter of one return (noise and LAS quantisation)
    sigmas: float  # a surface continued to a beam lands within sigmas × its own scatter
    margin: float  # a mixed return lies this far off both surfaces
    reach: int  # beams searched for the surfaces on each side
    max_gap: float  # largest foreground-background gap that still blends
    thin: int  # longest run of beams in front of a background marked as thin (0: off)
    thin_peak: int = 0  # longest such run falling to one nearest beam and rising from it
    footprint: float = 1.0  # beam footprint in steps (edges bleed by half of it)
    span: int = 99  # most beams between the two surfaces of a blend
    las_scale: float = 0.0
    min_offset: float = 0.0  # returns nearer a surface than this (across it) count as on it
    bleed_prob: float = 0.5  # least probability of a bleeding beam being past by min_offset
    axes: tuple[int, ...] = (0, 1)  # 0 azimuth, 1 elevation
    open_edges: bool = False  # judge returns at edges with nothing behind them
    fit_beams: int = 2  # beams of a face-on anchor's surface continued to a return (2 or 3)
    surface_sigma: float = 0.0  # range scatter of returns on a surface, edges left out (0: sigma)
    pool_rows: int = 5  # least run of rows whose first ramp beams are judged pooled (0: off)


def box_halfwidths(
    az: NDArray[np.float64], el: NDArray[np.float64], r: NDArray[np.float64], scale: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Half-widths (radians) of the azimuth and elevation a return's LAS quantisation box
    (± scale/2 in x, y and z) spans seen from the sensor: scale/2·(|cos az|+|sin az|)/ρ
    and scale/2·(cos el + |sin el|·(|cos az|+|sin az|))/r (ρ the horizontal distance)."""
    c = np.abs(np.cos(az)) + np.abs(np.sin(az))
    rho = np.maximum(r * np.cos(el), 1e-6)
    ha = 0.5 * scale * c / rho
    he = 0.5 * scale * (np.cos(el) + np.abs(np.sin(el)) * c) / np.maximum(r, 1e-6)
    return ha, he


def grid_index(
    az: NDArray[np.float64], step: float, off_grid: float = OFF_GRID
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Grid index of each angle on a regular grid of ``step`` (phase from the data) and
    whether the angle sits near its grid line (off by less than ``off_grid`` steps)."""
    i, off = grid_offsets(az, step)
    return i, off < off_grid


def grid_offsets(
    az: NDArray[np.float64], step: float
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Nearest grid line of each angle (``grid_index``) and how far off it the angle lies, in steps."""
    t = 2 * np.pi * az / step
    phase = float(np.angle(np.mean(np.exp(1j * t))) / (2 * np.pi) * step)
    f = (az - phase) / step
    i = np.round(f).astype(np.int64)
    return i, np.abs(f - i)


def pulse_numbers(t: NDArray[np.float64], max_jitter: float = 0.15) -> NDArray[np.int64] | None:
    """Each return's pulse number from its GPS time (the pulse period measured from the
    gaps between successive returns), or None when the times show no regular period
    (more than 5 % of them off their pulse by ``max_jitter`` periods or more)."""
    if t.size < 16 or not np.isfinite(t).all():
        return None
    order = np.argsort(t, kind="stable")
    ts = t[order] - t[order[0]]
    d = np.diff(ts)
    d = d[d > 0]
    if d.size < 8:
        return None
    # the shortest common gap is one period: the 5th percentile of the gaps lies in the
    # cluster of successive pulses when at least 5 % of them are
    period = float(np.percentile(d, 5))
    if period <= 0:
        return None
    # refined over ever longer gaps: gaps of k pulses add k periods each
    for most in (4, 64, 4096):
        k = np.round(d / period)
        use = (k >= 1) & (k <= most)
        if not use.any():
            return None
        period = float(d[use].sum() / k[use].sum())
    u = ts / period
    b = np.round(u)
    if np.mean(np.abs(u - b) >= max_jitter) > 0.05:
        return None
    out = np.empty(t.size, dtype=np.int64)
    out[order] = b.astype(np.int64)
    return out


def column_length(
    b: NDArray[np.int64], el: NDArray[np.float64], guess: float, step_el: float
) -> int:
    """Pulses per column: the lag L at which the return of pulse b + L (same row, next
    column) lies at the same elevation as pulse b's, searched outwards from ``guess``
    (up to 1.5× either way) on a sample of returns: a beam's elevation does not depend
    on the scene, only its blur. A lag whose median elevation change is under a quarter
    step ends the search (a lag off by one changes it by about a step)."""
    order = np.argsort(b)
    bs, es = b[order], el[order]
    pick = np.linspace(0, bs.size - 1, min(bs.size, 4000)).astype(np.int64)
    b0, e0 = bs[pick], es[pick]
    best, best_cost = 0, np.inf
    lo, hi = max(2, int(guess / 1.5)), int(np.ceil(guess * 1.5)) + 1
    g = int(np.clip(round(guess), lo, hi))
    for lag in sorted(range(lo, hi + 1), key=lambda v: (abs(v - g), v)):
        j = np.minimum(np.searchsorted(bs, b0 + lag), bs.size - 1)
        hit = bs[j] == b0 + lag
        if np.count_nonzero(hit) < 20:
            continue
        cost = float(np.median(np.abs(es[j[hit]] - e0[hit])))
        if cost < best_cost:
            best, best_cost = lag, cost
        if best_cost < 0.25 * step_el:
            break
    return best


def time_index(
    t: NDArray[np.float64],
    az: NDArray[np.float64],
    el: NDArray[np.float64],
    step_az: float,
    step_el: float,
    las_scale: float = 0.0,
    r: NDArray[np.float64] | None = None,
    agree: float = 0.95,
) -> tuple[NDArray[np.int64], NDArray[np.int64], float, float, int] | None:
    """Grid index (column, row) of every return from its firing order, with the steps
    in azimuth and elevation refitted on it and the pulses per column, or None.

    A scanner fires the rows of one column after the other, so pulse number =
    column × pulses per column + row (+ a constant). The column length is the lag
    between pulses at the same elevation (``column_length``); the row phase is the
    circular mean of (pulse − elevation in steps) over it, so every return counts,
    however blurred its angle by the LAS scale (``las_scale`` / √12 / range ``r``).
    The steps are then refitted by least squares (each angle weighted by its blur),
    and the result is used only when at least ``agree`` of the returns lie within half
    a step plus three times their blur of the beam their time gives.
    """
    b = pulse_numbers(t)
    if b is None:
        return None
    o = np.argsort(b, kind="stable")
    # in firing order (pulse − elevation in steps) is about constant along a column
    # and jumps by about a column length at the next one
    dx = np.diff(b[o] - el[o] / step_el)
    jump = dx[dx > 8.0]
    if jump.size < 4:
        return None
    per_col = column_length(b, el, float(np.median(jump)), step_el)
    if per_col < 2:
        return None
    y = el / step_el
    ph = np.angle(np.mean(np.exp(2j * np.pi * (b - y) / per_col)))
    c0 = int(np.round(ph / (2 * np.pi) * per_col))
    col = np.round((b - c0 - y) / per_col).astype(np.int64)
    row = b - c0 - col * per_col
    # the steps refitted on the indexes; azimuth unwrapped in firing order
    a = np.empty_like(az)
    a[o] = np.unwrap(az[o])
    blur = las_scale / np.sqrt(12.0) / np.maximum(r, 1e-6) if r is not None else 0.0
    w = 1.0 / (np.asarray(blur) ** 2 + (0.01 * min(step_az, step_el)) ** 2) * np.ones_like(a)

    def fit(ang: NDArray[np.float64], idx: NDArray[np.int64]) -> float:
        i = idx - np.average(idx, weights=w)
        return float(
            np.sum(w * i * (ang - np.average(ang, weights=w))) / max(np.sum(w * i * i), 1e-12)
        )

    s_az = fit(a, col) if np.ptp(col) > 0 else step_az
    s_el = fit(el, row) if np.ptp(row) > 0 else step_el
    if not (0.5 * step_az < s_az < 2 * step_az and 0.5 * step_el < s_el < 2 * step_el):
        return None
    bl = np.asarray(blur) / min(s_az, s_el)
    ra = a / s_az - col
    re = el / s_el - row
    tol = 0.5 + 3.0 * bl
    ok = (np.abs(ra - np.median(ra)) < tol) & (np.abs(re - np.median(re)) < tol)
    if np.mean(ok) < agree:
        return None
    return col, row, s_az, s_el, per_col


def mark_grid(
    rel: NDArray[np.float64],
    s: GridSettings,
    gps_time: NDArray[np.float64] | None = None,
    fov: tuple[float, float, float, float] | None = None,
) -> tuple[NDArray, NDArray, bool]:
    """Mixed returns of one scan position (``rel`` relative to the sensor).

    Returns (marked, judged, timed): returns not judged (off the grid, too near for the
    LAS scale to place them on their beam) are never marked. With ``gps_time`` (one
    per return) every return is placed on its beam by its firing order when the times
    agree with the angles (``time_index``; ``timed`` says so); otherwise by its angles.
    ``fov`` (first and last azimuth, lowest and highest elevation, radians;
    ``scan_geometry.field_of_view``) bounds the beams that were fired: a beam beyond
    it is no edge. None: the returns at hand bound it (the whole scan, not a block).
    With the firing order, each column fired its pulse count of rows from the lowest
    elevation up, returns or not.
    """
    n = rel.shape[0]
    marked = np.zeros(n, dtype=bool)
    r_all = np.linalg.norm(rel, axis=1)
    az = np.arctan2(rel[:, 1], rel[:, 0])
    el = np.arcsin(np.clip(rel[:, 2] / np.maximum(r_all, 1e-12), -1.0, 1.0))
    timed = None
    fired_rows = 0  # pulses per column, when the firing order gives it
    if gps_time is not None:
        timed = time_index(gps_time, az, el, s.step_az, s.step_el, s.las_scale, r_all)
    if timed is not None:
        ia, ie = timed[0], timed[1]
        s = replace(s, step_az=timed[2], step_el=timed[3])
        fired_rows = timed[4]
        judged = own = r_all > 1e-6
    else:
        ia, ie, judged, own = _angle_index(az, el, r_all, s)
    idx = np.flatnonzero(judged)
    if idx.size < 3:
        return marked, own, timed is not None
    ia, ie, r = ia[idx], ie[idx], r_all[idx]
    pad = 2 * s.reach + 4
    ia = ia - ia.min() + pad
    ie = ie - ie.min() + pad
    n_e = int(ie.max()) + pad + 1
    key = ia * n_e + ie
    order = np.argsort(key, kind="stable")
    key, r = key[order], r[order]
    find = _finder(key, (int(ia.max()) + pad + 1) * n_e)
    r_pad = np.append(r, np.nan)  # index r.size: no return
    out = np.zeros(r.size, dtype=bool)
    # Range change per beam across each axis (the smoother side): with the change along
    # the axis it gives a surface's incidence, so a range offset can be turned into a
    # distance off the surface (grazing ground looks flat along azimuth but is not).
    across: dict[int, NDArray[np.float64]] = {}
    for axis in (0, 1):
        stride = n_e if axis == 1 else 1  # neighbours along the other axis
        both = np.fmin(np.abs(r_pad[find(key + stride)] - r), np.abs(r_pad[find(key - stride)] - r))
        across[axis] = np.where(np.isfinite(both), both, 0.0)
    line_done = None
    bounds = _fov_bounds(fov, az[idx], el[idx], ia, ie, s)  # medians: in any order
    for axis in s.axes:
        pos = (key // n_e) if axis == 0 else (key % n_e)
        line = _Line(
            key, r_pad, find, n_e if axis == 0 else 1, s.reach + 2, across[axis], line_done
        )
        lo, hi = int(pos.min()), int(pos.max())
        if bounds is not None:
            lo, hi = min(lo, bounds[axis][0]), max(hi, bounds[axis][1])
        if axis == 1 and fired_rows:
            # every column fired fired_rows pulses upwards from its lowest beam, which
            # meets the ground around the sensor: rows above the highest return (a wall
            # top under an empty sky) were fired too
            hi = max(hi, lo + fired_rows - 1)
        level = None
        if axis == 1:
            # on a surface along azimuth: within the scatter of r - (r₋ + r₊)/2 (sd
            # sigma·sqrt(1.5)) of the mean of its azimuth neighbours one and two beams
            # away on either side
            tol = s.sigmas * s.sigma * np.sqrt(1.5)
            level = np.ones(r.size, dtype=bool)
            with np.errstate(invalid="ignore"):
                for k in (1, 2):
                    r_m, r_p = r_pad[find(key - k * n_e)], r_pad[find(key + k * n_e)]
                    level &= np.abs(0.5 * (r_m + r_p) - r) <= tol
        out |= _mixed_along(line, r, s, pos, axis, (lo, hi), level)
        line_done = line  # its arrays are free for the next axis
    if s.pool_rows > 0:
        out |= _pooled_edges(key, r, out, find, n_e, s)
    marked[idx[order]] = out
    return marked & own, own, timed is not None


def _pooled_edges(
    key: NDArray[np.int64],
    r: NDArray[np.float64],
    marked: NDArray[np.bool_],
    find: Any,
    n_e: int,
    s: GridSettings,
) -> NDArray[np.bool_]:
    """First beams of ramps along a vertical edge, judged pooled down the edge.

    The first beam of a ramp next to a face-on surface blends a small share of the
    other surface: with range noise near 1 cm and a gap under half a metre it lies
    4-5 sd off the surface, under what a single return must clear (about 7 sd of the
    surface scatter). Along a long edge the same beam recurs in every row, so the
    rows are judged together. A return p is a candidate on side sd when it is
    unmarked, its azimuth neighbour towards -sd is marked and lies off the surface by
    more than ``margin`` (the ramp), and its three
    next beams towards +sd are unmarked and lie on one face-on line (each within
    ``sigmas`` × σ√2 of the next, a difference of two returns). Its offset is p's
    range minus the least-squares line through those three continued to p's beam,
    (4 r₁ + r₂ − 2 r₃)/3, signed towards the marked neighbour, and p must lie short
    of that neighbour (between the surface and the ramp). Each offset scatters
    by σ√(10/3) (p's own σ and the continuation's σ√(7/3)), σ the measured range
    scatter of returns on a surface (``surface_sigma``). A run of at least
    ``pool_rows`` candidates in consecutive rows of one column is marked whole when
    its mean offset exceeds 3 σ√(10/3)/√n (3 standard errors of the mean of n
    offsets) and more than 80 % of its offsets point towards the ramp: noise alone
    gives either sign. With five rows that is 2.45 σ instead of about 7 σ per
    return. Along azimuth a scan of a full turn (its columns span 2π / step) wraps:
    the last column neighbours the first.
    """
    n = r.size
    sig = s.surface_sigma if s.surface_sigma > 0 else s.sigma
    col = key // n_e
    row = key - col * n_e
    c0, c1 = int(col.min()), int(col.max())
    turn = int(round(2 * np.pi / s.step_az))
    wrap = abs(2 * np.pi / s.step_az - turn) < 0.25 and c1 - c0 + 1 == turn
    r_pad = np.append(r, np.nan)
    m_pad = np.append(marked, False)

    def at(d: int) -> NDArray[np.intp]:
        c = col + d
        if wrap:
            c = (c - c0) % turn + c0
        return find(c * n_e + row)

    flat = s.sigmas * sig * np.sqrt(2.0)
    need = 3.0 * sig * np.sqrt(10.0 / 3.0)  # 3 standard errors of one offset
    add = np.zeros(n, dtype=bool)
    with np.errstate(invalid="ignore"):
        for sd in (1, -1):
            jn = at(-sd)
            cand = ~marked & m_pad[jn]
            if not cand.any():
                continue
            j1, j2, j3 = at(sd), at(2 * sd), at(3 * sd)
            r1, r2, r3 = r_pad[j1], r_pad[j2], r_pad[j3]
            cand &= ~m_pad[j1] & ~m_pad[j2] & ~m_pad[j3]
            cand &= (np.abs(r1 - r2) < flat) & (np.abs(r2 - r3) < flat)
            cont = (4.0 * r1 + r2 - 2.0 * r3) / 3.0
            # the marked neighbour off the surface by more than the margin: the ramp's
            # side, not noise (level with the surface its sign would follow the
            # continuation's own error, which p's offset shares)
            ramp = r_pad[jn] - cont
            cand &= np.abs(ramp) > s.margin
            off = (r - cont) * np.sign(ramp)
            # and p between the surface and that neighbour, as a ramp's first beam lies
            # (a surface of its own beyond the ramp is no blend of this edge)
            cand &= off < np.abs(ramp)
            cand &= np.isfinite(off)
            ci = np.flatnonzero(cand)
            if ci.size < s.pool_rows:
                continue
            # runs of consecutive rows in one column: consecutive keys (rows are padded)
            brk = np.flatnonzero(np.diff(key[ci]) != 1) + 1
            starts = np.r_[0, brk]
            lens = np.diff(np.r_[starts, ci.size])
            o = off[ci]
            mean = np.add.reduceat(o, starts) / lens
            pos_share = np.add.reduceat((o > 0).astype(np.float64), starts) / lens
            ok = (lens >= s.pool_rows) & (mean > need / np.sqrt(lens)) & (pos_share > 0.8)
            add[ci[np.repeat(ok, lens)]] = True
    return add


def _angle_index(
    az: NDArray[np.float64], el: NDArray[np.float64], r_all: NDArray[np.float64], s: GridSettings
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Grid index (azimuth, elevation) of every return from its angles, the returns near
    enough their grid lines to be judged, and those whose own beam the index gives for
    certain (``mark_grid`` without the firing order)."""
    ia, off_a = grid_offsets(az, s.step_az)
    ie, off_e = grid_offsets(el, s.step_el)
    judged = (off_a < OFF_GRID) & (off_e < OFF_GRID) & (r_all > 1e-6)
    own = judged  # returns whose own beam the grid index gives for certain
    if s.las_scale > 0:
        # the angle of a return lies anywhere in its quantisation box (half-widths ha, he
        # about the stored angle). It is on the grid when its box comes within OFF_GRID of
        # the nearest line: the returns near enough for the box to span a third of a step
        # all are, so blurred surfaces leave no holes in the range image (with 1 cm
        # coordinates at a 0.1° step, 3-15 % of the blends (per angle) at 6-10 m fell
        # more than OFF_GRID off their line, and an anchor needs three beams in a row).
        # A return whose box holds no other line than its nearest (off + half-width under
        # a step, in both angles) lies on that line: judged. The others on the grid still
        # fill the range image about it (their ranges are exact, their beams at most a
        # line off) as neighbours, never judged: left out, a judged blend lost the near
        # surface it lies between (1 cm coordinates within 18 m at 0.1°)
        ha, he = box_halfwidths(az, el, r_all, s.las_scale)
        ha, he = ha / s.step_az, he / s.step_el
        judged = (off_a < OFF_GRID + ha) & (off_e < OFF_GRID + he) & (r_all > 1e-6)
        own = judged & (off_a + ha < 1.0) & (off_e + he < 1.0)
    return ia, ie, judged, own


def _fov_bounds(
    fov: tuple[float, float, float, float] | None,
    az: NDArray[np.float64],
    el: NDArray[np.float64],
    ia: NDArray[np.int64],
    ie: NDArray[np.int64],
    s: GridSettings,
) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """Grid index range (azimuth, elevation) of the field of view ``fov``: each angle's
    offset from its index (the median over the returns) carries the bounds onto the grid."""
    if fov is None or ia.size == 0:
        return None
    a0, a1, e0, e1 = fov
    c = a0 + 0.5 * ((a1 - a0) % (2 * np.pi))  # middle of the field of view
    turn = 2 * np.pi

    def rel(a: NDArray[np.float64] | float) -> NDArray[np.float64]:
        return (np.asarray(a) - c + np.pi) % turn - np.pi

    off_a = float(np.median(rel(az) / s.step_az - ia))
    off_e = float(np.median(el / s.step_el - ie))
    return (
        (int(np.round(rel(a0) / s.step_az - off_a)), int(np.round(rel(a1) / s.step_az - off_a))),
        (int(np.round(e0 / s.step_el - off_e)), int(np.round(e1 / s.step_el - off_e))),
    )


class _Line:
    """Neighbours of every return along one axis of the grid: range and inverse range
    at each beam offset (NaN where no return). ``reuse``: a line of the same returns
    whose arrays are done with; its memory is taken over (fresh pages cost more than
    filling them)."""

    def __init__(self, key, r_pad, find, stride: int, reach: int, across, reuse=None) -> None:
        inv_pad = 1.0 / r_pad
        c_pad = np.append(across, 0.0)
        n = key.size
        self.R: dict[int, NDArray[np.float64]] = {0: r_pad[:n]}
        self.V: dict[int, NDArray[np.float64]] = {0: inv_pad[:n]}
        self.C: dict[int, NDArray[np.float64]] = {0: across}  # range change per beam across
        # index of the return there (n: none); the nearest beams kept, others on demand
        self.J = _Lookups(find, key, stride)
        offs = [sd * k for k in range(1, reach + 1) for sd in (1, -1)]
        shape = (len(offs), n)
        bufs = reuse.buffers if reuse is not None else None
        if bufs is None or bufs[1].shape != shape:
            bufs = (np.empty((2, n), dtype=np.int64), *(np.empty(shape) for _ in range(3)))
        self.buffers = bufs
        J, R, V, C = bufs
        # every offset's lookups and gathers in one compiled pass
        line_gather(
            key, find.lut, np.array(offs, dtype=np.int64) * stride, r_pad, inv_pad, c_pad, *bufs
        )
        for row, o in enumerate(offs):
            self.R[o], self.V[o], self.C[o] = R[row], V[row], C[row]
            if row < 2:
                self.J[o] = J[row]


class _Lookups(dict):
    """Index of the return at each beam offset along a line (``key.size``: none),
    looked up when first asked for."""

    def __init__(self, find, key: NDArray[np.int64], stride: int) -> None:
        super().__init__()
        self.find, self.key, self.stride = find, key, stride

    def __missing__(self, o: int) -> NDArray[np.int64]:
        j = self[o] = np.asarray(self.find(self.key + o * self.stride), dtype=np.int64)
        return j


class _Finder:
    """Index of the return at each wanted grid key (``key.size`` where none): a dense
    lookup table (``lut``, the last of equal keys) when the grid is at most 16 cells
    per return, binary search otherwise (``lut`` empty; the first of equal keys)."""

    def __init__(self, key: NDArray[np.int64], n_cells: int) -> None:
        n = key.size
        self.key = key
        small = np.int32 if n < 2**31 - 1 else np.int64  # half the table's memory traffic
        self.lut = np.zeros(0, dtype=small)
        if n_cells <= 16 * n:
            self.lut = np.full(n_cells, n, dtype=small)
            self.lut[key] = np.arange(n)

    def __call__(self, want: NDArray[np.int64]) -> NDArray[Any]:
        if self.lut.size:
            return self.lut[want]
        n = self.key.size
        j = np.minimum(np.searchsorted(self.key, want), n - 1)
        return np.where(self.key[j] == want, j, n)


def _finder(key: NDArray[np.int64], n_cells: int) -> _Finder:
    """Index of the return at each wanted grid key (``_Finder``)."""
    return _Finder(key, n_cells)


def _mixed_along(
    line: _Line,
    r: NDArray[np.float64],
    s: GridSettings,
    pos: NDArray[np.int64],
    axis: int,
    extent: tuple[int, int],
    level: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Mixed returns along one axis of the grid (``pos`` each return's index along it,
    ``extent`` the first and last index of the field of view; ``level``, along
    elevation: the returns level with their azimuth neighbours)."""
    n = r.size
    reach = s.reach
    R, V = line.R, line.V
    step = s.step_az if axis == 0 else s.step_el
    step_x = s.step_el if axis == 0 else s.step_az
    # least distance off a surface, across it: min_offset (the margin when 0). The margin
    # is a range scatter, tested on the range offset itself (``spread``); across a
    # grazing surface that scatter shrinks with the range offset
    across = s.min_offset if s.min_offset > 0 else s.margin
    # The LAS scale blurs each return's angle (sd scale/√12/range); on a surface whose
    # range changes by d per beam that adds d × the blur in steps to its range scatter.
    blur = s.las_scale / np.sqrt(12.0) / r / step
    spread_flat = s.sigmas * float(np.sqrt(s.sigma**2 + 0.0))

    def spread(i: int, slope: NDArray[np.float64] | float = 0.0) -> NDArray[np.float64]:
        """Scatter of a return about the surface through two beams continued i beams on
        (``slope``: the surface's range change per beam)."""
        factor = np.sqrt((1 + i) ** 2 + i**2 + 1)
        if np.isscalar(slope) and slope == 0.0:
            return spread_flat * factor  # no slope: the same scatter everywhere
        sl = np.broadcast_to(np.asarray(slope, dtype=np.float64), blur.shape)
        return spread_of(np.ascontiguousarray(sl), blur, s.sigma**2, s.sigmas, factor)

    # near[sd][i] / far[sd][i]: a surface i beams away on side sd, nearer / farther than p
    near: dict[int, dict[int, NDArray[np.bool_]]] = {1: {}, -1: {}}
    far: dict[int, dict[int, NDArray[np.bool_]]] = {1: {}, -1: {}}
    # off_end[sd]: an anchor on side sd whose surface, continued to p's beam, misses p
    # by more than its scatter and min_offset across it
    off_end = {1: np.zeros(n, dtype=bool), -1: np.zeros(n, dtype=bool)}
    # per side and beam offset: the beam is an anchor (on a surface), and p lies off it
    anchors: dict[int, dict[int, tuple[NDArray[np.bool_], NDArray[np.bool_]]]] = {1: {}, -1: {}}
    # off_blend[sd]: off by more than the surface itself could pull it (a footprint partly
    # on one surface answers at most half a footprint of beams back along it)
    off_blend = {1: np.zeros(n, dtype=bool), -1: np.zeros(n, dtype=bool)}
    # an anchor within max_gap already met nearer p on that side: the surface p ends
    met = {1: np.zeros(n, dtype=bool), -1: np.zeros(n, dtype=bool)}
    # along elevation: per side and beam offset, the returns whose nearer anchor's surface,
    # continued to their beam, passes beyond max_gap behind them, with that continuation
    hidden: dict[int, dict[int, tuple[NDArray[np.intp], NDArray[np.float64]]]] = {1: {}, -1: {}}
    flat_tol = s.sigmas * s.sigma * np.sqrt(2.0)  # a difference of two returns, face on
    on_surface = s.surface_sigma / s.sigma if s.surface_sigma > 0 else 1.0
    with np.errstate(invalid="ignore"):
        for sd in (1, -1):
            for i in range(1, reach + 1):
                a, a1, a2 = sd * i, sd * (i + 1), sd * (i + 2)
                ra = R[a]
                # on a surface: the line through its outer neighbours continues through
                # it, or (a surface only two beams wide) its outer neighbour agrees.
                # Off its surface: in range beyond the continuation's scatter, and across
                # the surface by more than min_offset (at grazing incidence a range offset
                # is mostly along the surface; the incidence at p's beam from the change
                # in inverse range per beam, which along a plane is even: tan = r ×
                # |Δ(1/r) per beam| / step). With fit_beams 3, an anchor nearer or farther
                # than p by more than the margin on a face-on surface (three beams on one
                # line, their range within the scatter of a difference) is continued by
                # the least-squares line through the three, whose continuation i beams on
                # scatters by sqrt(1/3 + (i+1)²/2) returns' sd against sqrt(i² + (i+1)²)
                # through two. Not on sloped surfaces: a bleeding end bends their third
                # beam, which the fit would carry to p. Three beams on one face-on line are
                # on a surface, so they scatter as returns on a surface do, not as the
                # median residual, which also counts edges and blends (shared-report
                # 4400: 10.8 mm against 9.0 mm; blends 7 cm off the line were missed).
                # Within max_gap of p: the anchor, or its surface continued to p's beam
                # (grazing ground a beam before a far wall's foot lies metres nearer than
                # the blend, its continuation half a metre behind it). p blends that
                # surface with a background ending within its beam (off_end) only within
                # max_gap of it (a return farther behind answers alone). off_blend: the
                # surface continued to p's beam, taken back half a footprint of beams
                # towards the anchor, is the farthest a return of that surface alone is
                # pulled; judged against the nearest anchor on that side only (met: the
                # surface p ends), as a farther one may be the bleeding returns of that
                # surface's other end. All of it in one compiled pass (``anchor_pass``).
                anchored, ok, near[sd][i], far[sd][i], front, beyond = anchor_pass(
                    r,
                    ra,
                    R[a1],
                    R[a2],
                    V[a],
                    V[a1],
                    V[a2],
                    line.C[a],
                    blur,
                    i,
                    s.sigma**2,
                    s.sigmas,
                    float(spread(0)),
                    float(np.sqrt((1 + 1) ** 2 + 1**2 + 1)),
                    float(np.sqrt((1 + i) ** 2 + i**2 + 1)),
                    s.fit_beams >= 3,
                    float(flat_tol),
                    float(
                        on_surface
                        * np.sqrt((4.0 / 3.0 + (i + 1) ** 2 / 2.0) / ((1 + i) ** 2 + i**2 + 1))
                    ),
                    s.margin,
                    step,
                    step_x,
                    across,
                    s.max_gap,
                    s.footprint / 2.0,
                    off_end[sd],
                    met[sd],
                    off_blend[sd],
                )
                anchors[sd][i] = (anchored, ok)
                # the front of a thin object one beam wide is an anchor too (it has no
                # second beam on its line): its neighbours either side lie behind it by
                # more than a convex surface through it recedes in one beam (step × range)
                # and, seen from beyond, on no surface of their own (blends of the object
                # with what lies behind; a wall running up to the object is no blend)
                behind_c = None
                if axis == 1 and level is not None:
                    behind_c = np.flatnonzero(near[sd][i] & ~level)  # used below
                if i + 3 <= reach + 2:
                    # p behind the anchor by more than margin + step × range, picked first
                    cp = np.flatnonzero(front)
                    ra_c = ra[cp]
                    lim = s.margin + step * ra_c
                    inner = (R[sd * (i - 1)] if i > 1 else r)[cp]
                    cp = cp[
                        (R[a1][cp] - ra_c > lim) & (inner - ra_c > lim) & (r[cp] - ra_c < s.max_gap)
                    ]
                    if cp.size:
                        keep = ~_on_line(R, cp, a1, sd, s, step) & ~_on_line(
                            R, cp, sd * (i - 1), -sd, s, step
                        )
                        near[sd][i][cp[keep]] = True
                if axis == 1:
                    # a nearer surface (grazing ground) whose continuation to p's beam
                    # passes more than max_gap behind p: where a farther anchor lies in
                    # front of that continuation, it hides the ground running on under it
                    # (a wall's foot), and p blends the two (paired below)
                    cc = np.flatnonzero(beyond)
                    v = V[a][cc] + (V[a][cc] - V[a1][cc]) * i
                    hidden[sd][i] = (cc, np.where(v > 0, 1.0 / v, np.inf))
                # a beam seen past a thin object (the pole before a wall's one beam between
                # its blends and a board's ramp) has no line of its own outwards: the
                # surface beyond the object's run, continued across it, anchors it
                cx, dx = _past_thin_run(line, R, r, anchored, s, sd, i, blur, step, across)
                if cx.size:
                    rx, rax = r[cx], ra[cx]
                    close = np.fmin(np.abs(rax - rx), dx) < s.max_gap
                    far[sd][i][cx[close & (rax > rx + s.margin)]] = True
                    near[sd][i][cx[close & (rax < rx - s.margin)]] = True
                if axis == 1 and level is not None:
                    # a nearer surface (grazing ground) whose continuation to p's beam
                    # passes behind p (within max_gap): p lies in front of the ground
                    # running on under an object above (a board's or wall's foot), so the
                    # ground counts as the farther surface there, paired below with a
                    # nearer one above. Not when p lies on a surface along azimuth (a
                    # wall's foot row, the ground continued passing behind the wall)
                    cb = behind_c
                    if cb is not None and cb.size:
                        v = V[a][cb] + (V[a][cb] - V[a1][cb]) * i
                        behind = np.where(v > 0, 1.0 / v, np.inf) > r[cb] + s.margin
                        far[sd][i][cb[behind]] = True
                # along azimuth, the last beam of the field of view on this side (its last
                # return, within the one beam the bound's rounding may add), behind p, with
                # every beam out to it farther than the one before (a ramp into it, from
                # the nearer surface): a background there shows one beam at most, no line to
                # anchor it, so that beam counts as the farther surface (paired below with
                # an anchor nearer than p on the other side, as a one-beam front is)
                if axis == 0:
                    ce = np.flatnonzero(sd * (extent[1 if sd == 1 else 0] - pos - a) <= 1)
                    ra_e, r_e = ra[ce], r[ce]
                    ce = ce[
                        np.isnan(R[a + sd][ce]) & (ra_e > r_e + s.margin) & (ra_e < r_e + s.max_gap)
                    ]
                    if ce.size:
                        # each step of the ramp, from p's inner neighbour out to the edge,
                        # exceeds margin + step × range: more than a surface at up to 45°
                        # incidence recedes in one beam (the one-beam front's bound; an
                        # oblique wall receding into the edge is no ramp, nor a dip at p)
                        prev = r[ce]
                        mono = R[-sd][ce] < prev - s.margin - step * prev
                        for j in range(1, i + 1):
                            rj = R[sd * j][ce]
                            mono &= rj > prev + s.margin + step * rj
                            prev = rj
                        # and p on no surface: off the line of its next two beams either way
                        # by more than the range scatter of that line continued one beam
                        # (sqrt(6) returns' sd; the ramp's beams are placed by their firing
                        # order, no LAS blur)
                        tol_line = s.sigmas * s.sigma * np.sqrt(6.0)
                        for w in (-sd, sd) if i >= 2 else (-sd,):
                            v = 2.0 / R[w][ce] - 1.0 / R[2 * w][ce]
                            cont = np.where(v > 0, 1.0 / v, np.inf)
                            mono &= ~(np.abs(cont - r[ce]) <= tol_line)
                        far[sd][i][ce[mono]] = True
    # A blend spans about a footprint: at most ``span`` beams lie between the surfaces
    # (a strip of ground seen between a board's top and the wall behind is longer).
    between = np.zeros(n, dtype=bool)
    paired = np.zeros(n, dtype=bool)
    for sd in (1, -1):
        upto = np.zeros(n, dtype=bool)
        nearer = []
        for i in range(1, reach + 1):
            upto = upto | near[-sd][i]
            nearer.append(upto)
        for j in range(1, min(reach, s.span) + 1):
            paired |= far[sd][j] & nearer[min(s.span + 1 - j, reach) - 1]
            for k in range(1, min(s.span + 1 - j, reach) + 1) if hidden[-sd] else ():
                cc, cont = hidden[-sd][k]
                between[cc] |= far[sd][j][cc] & (cont > R[sd * j][cc])
    # a return on a face-on strip stepping nearer past one end and farther past the other
    # (a wall between a nearer object's edge and a farther surface) pairs no anchors
    cand = np.flatnonzero(paired)
    between[cand[~_step_run(R, r, s, flat_tol, cand)]] = True
    if axis == 0:
        # along elevation the ground recedes monotonically from the sensor up to a
        # wall's foot: runs there are left to the rules above
        between |= _cascade(R, V, r, near, far, reach, s, blur, step, across)
    # Open edges: nothing answers beyond p (no return, or a background farther than
    # max_gap), yet p lies off the surface it ends, continued to its beam. The part of
    # a footprint still on a sloped surface answers at that part's mean range, not
    # where the central ray meets the surface: nearer on a receding one (ground towards
    # the range limit), farther on an approaching one. A blend with nothing.
    # p must not lie on its inner neighbour's surface (a board's top row with the ground
    # below it is in front of the ground's continuation, yet on the board).
    # With a footprint of more than a step the ramp into nothing spans several beams
    # (grazing ground at the range limit: every beam whose footprint straddles the limit
    # answers from its nearer part, and a beam answers while any of it meets the
    # ground): a beam off the surface it ends whose next beam outwards is such a blend
    # is one too, up to a footprint of beams.
    chain = int(np.ceil(s.footprint))
    with np.errstate(invalid="ignore"):
        for sd in (1, -1):
            inside = (pos + sd >= extent[0]) & (pos + sd <= extent[1])
            open_ = inside & ~(R[sd] <= r + s.max_gap)
            own = np.abs(R[-sd] - r) <= spread(0, np.abs(R[-sd] - R[-2 * sd]))
            if not s.open_edges:
                # within min_offset of the inner neighbour in range: on its surface
                own |= np.abs(R[-sd] - r) <= s.min_offset
            off = (off_end[-sd] if s.open_edges else off_blend[-sd]) & ~own
            ends = open_ & off
            if not s.open_edges:
                # the inner surface, continued past p, would answer beyond max_gap: it
                # recedes out of reach (grazing ground towards the range limit) and
                # does not end at p, so no background ends within p's beam
                v_on = V[-sd] + (V[-sd] - V[-2 * sd]) * 2.0
                ends &= ~((v_on <= 0) | (1.0 / v_on > r + s.max_gap))
            for _ in range(1, chain):
                ends |= off & np.append(ends, False)[line.J[sd]]
            between |= ends
    if s.thin > 0:
        between |= _thin_runs(R, V, line.C, r, s, step, step_x)
        if axis == 0:
            between |= _hidden_gaps(R, V, r, anchors, s)
        between |= _thin_runs_hidden(R, V, line.C, r, s, step, step_x)
    if s.open_edges:
        between |= _bleeding(R, V, line.C, r, s, step, step_x, pos, extent, oblique=axis == 0)
    return between


def _past_thin_run(
    line: _Line,
    R: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    anchored: NDArray[np.bool_],
    s: GridSettings,
    sd: int,
    i: int,
    blur: NDArray[np.float64],
    step: float,
    across: float,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Beams ``i`` beams from p on side ``sd`` that lie on a surface seen past a thin
    object, and p's range offset from that surface, for the returns p off it.

    A surface seen between the blends of a thin object and a nearer edge (a wall's one
    beam between a pole narrower than the footprint and the ramp into a board) shows
    no line of its own outwards: its next beams are the object's run. The beam (not
    anchored otherwise) is on the surface beyond the run when every beam of the run,
    at most ``s.thin`` of them, lies nearer than it by more than the margin, the first
    beam past the run lies behind the run's last, and the line through the first two
    beams past the run, continued across it, lands on the beam (within the scatter of
    a two-beam line continued that far, as an anchor's own line is judged). p is off
    that surface when the line, continued on to p's beam, misses p by more than its
    scatter there and by more than ``across`` across the surface (its incidence from the
    line's change in inverse range per beam).
    Returns the indexes of those p and their range offsets."""
    a = sd * i
    c = edge_drops(R[sd * (i + 1)], R[a], r, anchored, s.margin)
    if c.size == 0:
        return c, np.zeros(0)
    j = line.J
    lut = j.find.lut
    return past_run(
        c, j.key, lut, j.stride, r, blur, a, sd, s.thin, s.margin, s.sigma, s.sigmas, step, across
    )


def _step_run(
    R: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    s: GridSettings,
    flat_tol: float,
    c: NDArray[np.intp],
) -> NDArray[np.bool_]:
    """Returns on a face-on strip of at least three beams that steps nearer past one end
    and farther past the other: a wall seen between a nearer object's edge (often the
    flat run of blends of a pole narrower than the footprint, which reads as a surface)
    and a ramp into a farther surface. Such a return lies on its strip, so it is no blend
    of the anchors either side of the strip. Each beam of the strip, p's neighbour first,
    lies within ``flat_tol`` (a difference of two returns, face on, in the scatter the
    anchors take) of the one before, out to ``s.reach`` beams; the first beam past
    each end lies nearer by more than the margin on one side and farther by more than
    the margin on the other. A pole's flat run of blends lies nearer than both sides (it
    steps farther at both ends), so it is not such a strip. Judged for the returns ``c``."""
    n = c.size
    r = r[c]
    ext: dict[int, NDArray[np.int64]] = {}
    past: dict[int, NDArray[np.float64]] = {}
    with np.errstate(invalid="ignore"):
        for sd in (1, -1):
            k = np.zeros(n, dtype=np.int64)
            on = np.ones(n, dtype=bool)
            stopped = np.zeros(n, dtype=bool)
            prev = r
            out = np.full(n, np.nan)  # range of the first beam past the strip's end
            for i in range(1, s.reach + 1):
                cur = R[sd * i][c]
                on &= np.abs(cur - prev) <= flat_tol
                k += on
                ends = ~on & ~stopped
                out[ends] = cur[ends]
                stopped |= ends
                prev = np.where(on, cur, prev)
            ext[sd], past[sd] = k, out
        run = 1 + ext[1] + ext[-1]
        stair = np.zeros(n, dtype=bool)
        for sd in (1, -1):
            stair |= (past[sd] > r + s.margin) & (past[-sd] < r - s.margin)
    return (run >= 3) & stair


def _on_line(
    R: dict[int, NDArray[np.float64]],
    c: NDArray[np.intp],
    o: int,
    away: int,
    s: GridSettings,
    step: float,
) -> NDArray[np.bool_]:
    """Whether the returns at beam offset ``o`` (of the returns ``c``) lie on the line
    through their next two beams in direction ``away`` (inverse range, within the
    scatter of that line continued one beam, as an anchor is judged)."""
    r1, r2 = R[o + away][c], R[o + 2 * away][c]
    with np.errstate(invalid="ignore", divide="ignore"):
        v = 2.0 / r1 - 1.0 / r2
        cont = np.where(v > 0, 1.0 / v, np.inf)
        sd = np.sqrt(s.sigma**2 + (np.abs(r1 - r2) * s.las_scale / np.sqrt(12.0) / r1 / step) ** 2)
    return np.abs(cont - R[o][c]) <= s.sigmas * sd * np.sqrt(6.0)


def _cascade(
    R: dict[int, NDArray[np.float64]],
    V: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    near: dict[int, dict[int, NDArray[np.bool_]]],
    far: dict[int, dict[int, NDArray[np.bool_]]],
    reach: int,
    s: GridSettings,
    blur: NDArray[np.float64],
    step: float,
    across: float,
) -> NDArray[np.bool_]:
    """Returns between a nearer and a farther surface whose beams, out to each anchor,
    move one way (farther towards the farther anchor, nearer towards the nearer) by more
    than the margin at every beam, each of them off the anchor's surface: a surface
    narrower than the footprint between two others (a board seen between a nearer one
    and the wall) shows no anchored return of its own, so the ramps of its two edges
    join into one run of blends longer than ``span``. A run whose beams lie on the
    anchor's surface is that surface (an oblique one ending at p), not a blend."""
    n = r.size
    out = np.zeros(n, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for sd in (1, -1):
            # candidates: monotone runs out to an anchor on both sides
            got = {}
            for side, sign, anchors in ((sd, 1.0, far[sd]), (-sd, -1.0, near[-sd])):
                run = np.ones(n, dtype=bool)
                hit = np.zeros(n, dtype=bool)
                prev = r
                for i in range(1, reach + 1):
                    cur = R[side * i]
                    run &= sign * (cur - prev) > s.margin
                    hit |= run & anchors[i]
                    prev = cur
                got[side] = hit
            c = np.flatnonzero(got[sd] & got[-sd])
            if c.size == 0:
                continue
            ok = np.ones(c.size, dtype=bool)
            for side, sign, anchors in ((sd, 1.0, far[sd]), (-sd, -1.0, near[-sd])):
                run = np.ones(c.size, dtype=bool)
                hit = np.zeros(c.size, dtype=bool)
                prev = r[c]
                for i in range(1, reach + 1):
                    cur = R[side * i][c]
                    run &= sign * (cur - prev) > s.margin
                    prev = cur
                    cand = run & anchors[i][c]
                    if i > 1 and cand.any():
                        # every beam between p and the anchor off the anchor's surface
                        va, vb = V[side * i][c], V[side * (i + 1)][c]
                        slope = np.abs(R[side * i][c] - R[side * (i + 1)][c])
                        # beams that each lie on the line of their two neighbours form a
                        # surface (an oblique board, however it curves in inverse range)
                        flat = np.ones(c.size, dtype=bool) if i > 2 else np.zeros(c.size, bool)
                        for t in range(1, i):
                            v = va + (va - vb) * (i - t)
                            sd_t = np.sqrt(s.sigma**2 + (slope * blur[c]) ** 2)
                            k = i - t
                            tol = s.sigmas * sd_t * np.sqrt((1 + k) ** 2 + k**2 + 1)
                            rt = R[side * t][c]
                            dev = np.abs(np.where(v > 0, 1.0 / v, np.inf) - rt)
                            # across the surface too (its incidence from the change in
                            # inverse range per beam), as p itself is judged
                            cos_inc = 1.0 / np.sqrt(1.0 + (rt * np.abs(va - vb) / step) ** 2)
                            cand &= (dev > tol) & (dev * cos_inc > across)
                            v_in = V[side * (t - 1)][c] if t > 1 else 1.0 / r[c]
                            mid = 2.0 / (v_in + V[side * (t + 1)][c])
                            tol1 = s.sigmas * sd_t * np.sqrt(6.0)
                            flat &= np.abs(mid - rt) <= tol1
                        cand &= ~flat
                    hit |= cand
                ok &= hit
            out[c[ok]] = True
    return out


def _bleeding(
    R: dict[int, NDArray[np.float64]],
    V: dict[int, NDArray[np.float64]],
    C: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    s: GridSettings,
    step: float,
    step_x: float,
    pos: NDArray[np.int64],
    extent: tuple[int, int],
    oblique: bool = True,
) -> NDArray[np.bool_]:
    """Returns of a surface beyond its edge: where nothing answers behind an edge (no
    return, or a background beyond ``max_gap``), a beam whose footprint still touches the
    surface answers on its own central ray, up to half a footprint past the edge.
    The k-th beam before such an edge has its centre x steps past it, x even in
    [footprint/2 - k, footprint/2 - k + 1); it is marked when the probability of lying
    more than ``min_offset`` off the surface exceeds ``bleed_prob`` (``_bleed_prob``:
    on an oblique surface its range says where the edge fell; ``oblique`` only along
    azimuth: along elevation an open edge of a receding surface can be grazing ground at
    the range limit, which does not end there). Beams outside the field of view
    (``extent``) are not edges, nor beams the surface, continued, would reach only
    beyond ``max_gap``."""
    out = np.zeros(r.size, dtype=bool)
    half = s.footprint / 2.0
    # a shift sideways, which range noise does not blur: min_offset (the margin if 0)
    least = s.min_offset if s.min_offset > 0 else s.margin
    with np.errstate(invalid="ignore", divide="ignore"):
        for sd in (1, -1):
            # on a surface seen from the inner side
            # (or nearer than it: on a receding surface, e.g. grazing ground, the part of
            # the footprint still on it lies nearer than where the central ray would meet it)
            tol = s.sigmas * s.sigma * np.sqrt(6)
            # along an oblique surface the part of the footprint still on it answers
            # up to half a footprint of beams back: farther than its continuation on an
            # approaching surface, and the beams before the edge differ in range
            # (NaN where a beam is missing: no candidate there, as without the pull)
            slope = np.abs(R[-sd] - R[-2 * sd]) if oblique else 0.0
            inner = r - 1.0 / (2 * V[-sd] - V[-2 * sd]) <= tol + slope * half
            same = np.ones(r.size, dtype=bool)
            for k in range(1, min(int(np.ceil(half + 1)), s.reach + 2)):
                beyond = R[sd * k]
                inside = (pos + sd * k >= extent[0]) & (pos + sd * k <= extent[1])
                edge = inside & ~(beyond <= r + s.max_gap)  # no return, or far behind
                # the inner surface, continued to that beam, would have answered within
                # max_gap of p: a receding surface (grazing ground towards the range
                # limit) continues out of reach there, which is no edge
                v = V[-sd] + (V[-sd] - V[-2 * sd]) * (k + 1)
                edge &= (v > 0) & (1.0 / v <= r + s.max_gap)
                c = np.flatnonzero(inner & same & edge & (half - k + 1 > 0))
                if c.size:
                    # the surface from two beams inside, clear of the footprint's reach
                    # from the edge (2 half-footprints from it)
                    j = int(np.clip(np.ceil(2 * half - k + 1), 1, s.reach))
                    prob = _bleed_prob(
                        r[c],
                        V[-sd * j][c],
                        V[-sd * (j + 1)][c],
                        V[-sd * (j + 2)][c],
                        C[-sd * j][c],
                        R[-sd * j][c],
                        (R[-sd] - R[-2 * sd])[c],
                        j,
                        s,
                        step,
                        step_x,
                        half - k,
                        least,
                        oblique,
                    )
                    out[c[prob > s.bleed_prob]] = True
                same &= np.abs(beyond - r) <= s.margin + k * slope
    return out


def _bleed_prob(
    r: NDArray[np.float64],
    v1: NDArray[np.float64],
    v2: NDArray[np.float64],
    v3: NDArray[np.float64],
    c1: NDArray[np.float64],
    r1: NDArray[np.float64],
    d_near: NDArray[np.float64],
    j: int,
    s: GridSettings,
    step: float,
    step_x: float,
    x0: float,
    least: float,
    oblique: bool = True,
    n: int = 32,
) -> NDArray[np.float64]:
    """Probability that a beam whose centre lies x steps past a surface's edge, x even in
    [x0, x0 + 1), lies more than ``least`` off the surface, given its range.

    The part of the footprint (half-width h = footprint/2 steps) still on the surface,
    [x - h, edge], answers at its mean range: (x + h)/2 beams back from the beam's own,
    so along a surface whose inverse range changes by g per beam (``v2`` → ``v1``, two
    beams ``j`` and ``j`` + 1 inside, on one surface with ``v3`` at ``j`` + 2) the
    return lies g (x + h)/2 off the surface continued to its beam, and is pulled back
    over the surface by that offset times sin(incidence).
    Its distance off the surface is then the offset across it (cos(incidence)) and
    what remains past the edge. Face on (g = 0) the range says nothing and this is the
    share of x past the edge by more than ``least``; on an oblique surface the range,
    with its scatter, weighs each x. Where the beams inside are on no one surface (a
    narrow board's other end), or their change in range per beam is within the scatter
    of a difference of two returns (the incidence is not resolved), or the two beams next
    to the beam (``d_near``: their change in range per beam) do not keep at least half
    that change with its sign (pulled back by half a beam per beam at most, they do on
    one surface; not on a blend's ramp), the face-on share stands.
    """
    half = s.footprint / 2.0
    face_on = np.clip(x0 + 1.0 - least / (step * r), 0.0, 1.0)  # x even in [x0, x0 + 1)
    if not oblique:
        return face_on
    # the three beams inside lie on one surface (the line through the outer two continues
    # through the inner one within its scatter, in range), its change in range per beam
    # is resolved, and the two beams next to the beam keep at least half of it
    tol = s.sigmas * s.sigma * np.sqrt(2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        on_one = np.abs(1.0 / (2 * v2 - v3) - 1.0 / v1) <= s.sigmas * s.sigma * np.sqrt(6.0)
        d_far = 1.0 / v1 - 1.0 / v2
        use = on_one & (np.abs(d_far) > tol) & (d_near * np.sign(d_far) >= np.abs(d_far) / 2 - tol)
        use &= v1 + (v1 - v2) * j > 0
    u = np.flatnonzero(use)
    if u.size == 0:
        return face_on
    r, v1, v2, c1, r1 = r[u], v1[u], v2[u], c1[u], r1[u]
    x = x0 + (np.arange(n) + 0.5) / n  # (n,)
    g = v1 - v2
    v_p = v1 + g * j  # the surface continued to the beam
    tan_a = r * np.abs(g) / step
    tan_x = r * c1 / r1**2 / step_x
    cos_inc = 1.0 / np.sqrt(1.0 + tan_a**2 + tan_x**2)
    shift = np.clip(x + half, 0.0, 2 * half) / 2.0  # beams from the centre to the part's mean
    v_ret = v_p[:, None] - g[:, None] * shift[None, :]
    dr = np.abs(1.0 / v_ret - 1.0 / v_p[:, None])
    across = dr * cos_inc[:, None]
    along = np.maximum(x, 0.0)[None, :] * (step * r)[:, None] * np.sqrt(1.0 + tan_a**2)[:, None]
    along = np.maximum(along - dr * (tan_a * cos_inc)[:, None], 0.0)
    off = np.hypot(across, along) > least
    # the beam's range against each x: its inverse range scatters by sigma / r^2 about
    # the continuation (two beams continued j on)
    sd_v = s.sigma * np.sqrt((1 + j) ** 2 + j**2 + 1) / r**2
    z = (1.0 / r[:, None] - v_ret) / sd_v[:, None]
    w = np.exp(-0.5 * np.minimum(z * z, 700.0))
    tot = w.sum(axis=1)
    p = (w * off).sum(axis=1) / np.where(tot > 0, tot, 1.0)
    out = face_on.copy()
    out[u] = np.where(tot > 1e-12, p, off.mean(axis=1))
    return out


def _thin_runs(
    R: dict[int, NDArray[np.float64]],
    V: dict[int, NDArray[np.float64]],
    C: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    s: GridSettings,
    step: float,
    step_x: float,
) -> NDArray[np.bool_]:
    """Returns in a run of at most ``s.thin`` beams lying in front of one surface that
    continues behind them (the surface either side, continued across the run, agrees
    with the other side's beam, unless that beam is a blend of a ramp into a farther
    surface; or the one beam seen on each side agrees with the other, a face-on surface),
    by more than ``min_offset`` across that surface (the margin when 0; ``C``: range change
    per beam across the axis; grazing ground before a pole's foot is not in front of it)."""
    out = np.zeros(r.size, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        # runs longer than s.thin fall to one nearest beam and rise from it by more than
        # the margin at every beam: only returns off both neighbours by that much
        steep = np.flatnonzero((np.abs(R[1] - r) > s.margin) & (np.abs(R[-1] - r) > s.margin))
        for L in range(1, max(s.thin, s.thin_peak) + 1):
            # p at position q (0..L-1) within a run of L beams: background at -(q+1) and +(L-q)
            for q in range(L):
                lo, hi = -(q + 1), L - q
                if -lo + 1 > s.reach + 2 or hi + 1 > s.reach + 2:
                    continue
                # the rest is judged on these few only
                if s.thin < L:
                    d0, d1 = R[lo][steep] - r[steep], R[hi][steep] - r[steep]
                    behind = (d0 > s.margin) & (d1 > s.margin) & (d0 < s.max_gap)
                    c = steep[np.flatnonzero(behind & (d1 < s.max_gap))]
                else:
                    c = behind_both(r, R[lo], R[hi], s.margin, s.max_gap)
                if c.size == 0:
                    continue
                rc, rb0, rb1 = r[c], R[lo][c], R[hi][c]
                # the run's beams all lie in front of the background
                keep = np.ones(c.size, dtype=bool)
                for m in range(lo + 1, hi):
                    keep &= R[m][c] < np.minimum(rb0, rb1) - s.margin
                if s.thin < L:
                    # longer than a run with one return off the ramps: the run shows at
                    # most one return of the object. Two returns of a face-on object lie
                    # within the margin of each other
                    run = np.stack([R[m][c] if m else rc for m in range(lo + 1, hi)])
                    keep &= _one_nearest(run, s.margin)
                # the background continues behind the run: each side's surface,
                # continued across the run, lands on the other side's beam
                v0, v1 = V[lo][c], V[hi][c]
                v_left = v0 + (v0 - V[lo - 1][c]) * (hi - lo)
                v_right = v1 + (v1 - V[hi + 1][c]) * (hi - lo)
                tol = s.sigmas * s.sigma * np.sqrt((1 + L) ** 2 + L**2 + 1)
                from_left = np.abs(1.0 / v_left - rb1) <= tol
                from_right = np.abs(1.0 / v_right - rb0) <= tol
                # the beam a surface lands on is that surface's, not a blend in a ramp into
                # a farther one: the beam beyond it lies no farther than the landing beam
                # or the surface continued one beam on, by more than the margin, or
                # beyond max_gap of it (too far to have blended with it: a wall's end)
                v_on = (v_left + (v0 - V[lo - 1][c]), v_right + (v1 - V[hi + 1][c]))
                r_on = [np.where(v > 0, 1.0 / v, np.inf) for v in v_on]  # receding: any
                far_l, far_r = R[hi + 1][c], R[lo - 1][c]
                from_left &= ~(
                    (far_l > np.fmax(rb1, r_on[0]) + s.margin) & (far_l < rb1 + s.max_gap)
                )
                from_right &= ~(
                    (far_r > np.fmax(rb0, r_on[1]) + s.margin) & (far_r < rb0 + s.max_gap)
                )
                # or, seen one beam on each side (the beams beyond give no return or lie
                # on nearer surfaces), a face-on background agrees with itself across the
                # run: the two beams within the scatter of a difference of two returns. Not
                # when a beam beyond lies farther still: the two may be blends of a ramp
                # into a farther surface (a board's face between its two edges' ramps)
                level = np.abs(rb0 - rb1) <= s.sigmas * s.sigma * np.sqrt(2.0)
                level &= ~(R[lo - 1][c] > rb0 + s.margin) & ~(R[hi + 1][c] > rb1 + s.margin)
                cont = from_left | from_right | level
                # the incidence of the background on a side whose surface continues
                # across the run (the other side's outer beam may lie past the
                # background's own edge: a pole before a wall's end)
                tan_l = np.where(from_left, np.abs(v0 - V[lo - 1][c]), np.inf)
                tan_r = np.where(from_right, np.abs(v1 - V[hi + 1][c]), np.inf)
                # a level background's incidence from its change across the run
                tan_l = np.fmin(tan_l, np.where(level, np.abs(v0 - v1) / (hi - lo), np.inf))
                tan_a = rc * np.fmin(tan_l, tan_r) / step
                tan_x = rc * np.where(tan_l <= tan_r, C[lo][c], C[hi][c]) / rb0**2 / step_x
                least = s.min_offset if s.min_offset > 0 else s.margin
                in_front = (rb0 - rc) / np.sqrt(1.0 + tan_a**2 + tan_x**2) > least
                out[c[keep & cont & in_front]] = True
    return out


def _one_nearest(run: NDArray[np.float64], margin: float) -> NDArray[np.bool_]:
    """Runs (beams × returns) falling to one nearest beam and rising from it: every beam
    nearer than the one before by more than ``margin`` down to the nearest, every beam
    after it farther by more than ``margin``."""
    k = np.argmin(np.where(np.isfinite(run), run, np.inf), axis=0)
    d = np.diff(run, axis=0)
    j = np.arange(d.shape[0])[:, None]
    with np.errstate(invalid="ignore"):
        return np.asarray(np.where(j < k[None], -d > margin, d > margin).all(axis=0), dtype=bool)


def _hidden_gaps(
    R: dict[int, NDArray[np.float64]],
    V: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    anchors: dict[int, dict[int, tuple[NDArray[np.bool_], NDArray[np.bool_]]]],
    s: GridSettings,
) -> NDArray[np.bool_]:
    """Returns in a run of at most ``s.thin`` unanchored beams between the nearest anchor on
    each side, off both anchors' surfaces, that rises from one anchor to a peak and falls
    from it to the other (every beam farther than the one before, then nearer, by more than
    the margin), the peak with a beam of the run on each side of it, farther than both
    anchors and both their surfaces continued to it by more than the margin and within
    ``max_gap`` of the farther anchor. A third surface seen between the two only through a
    gap narrower than the footprint (the wall behind a board, between the board's edge and
    a nearer wall's edge) shows no return of its own: every return there blends it with an
    edge, so the run climbs to it and falls from it. A peak next to an anchor has no blend
    on that side (a plain occlusion, nothing that says the gap is narrower than the beam).
    The dual of a thin object (``_thin_runs``)."""
    n = r.size
    out = np.zeros(n, dtype=bool)
    reach = max(anchors[1]) if anchors[1] else 0
    first = {}
    for sd in (1, -1):
        f = np.zeros(n, dtype=np.int64)  # 0: no anchor within reach
        for i in range(reach, 0, -1):
            f = np.where(anchors[sd][i][0], i, f)
        first[sd] = f
    with np.errstate(invalid="ignore", divide="ignore"):
        for fl in range(1, reach + 1):
            for fr in range(1, min(reach, s.thin + 1 - fl) + 1):
                if fl + fr - 1 < 3:  # the peak and a beam either side of it
                    continue
                sel = (first[-1] == fl) & (first[1] == fr) & anchors[-1][fl][1] & anchors[1][fr][1]
                c = np.flatnonzero(sel)
                if c.size == 0:
                    continue
                rl, rr = R[-fl][c], R[fr][c]
                run = np.stack([R[t][c] if t else r[c] for t in range(-fl + 1, fr)])  # (L, c)
                full = np.vstack([rl[None], run, rr[None]])
                k = np.argmax(np.where(np.isfinite(run), run, -np.inf), axis=0) + 1  # in full
                keep = np.isfinite(run).all(axis=0) & (k >= 2) & (k <= run.shape[0] - 1)
                # rising to the peak, falling after it, by more than the margin at every beam
                d = np.diff(full, axis=0)  # (L + 1, c)
                j = np.arange(d.shape[0])[:, None]
                keep &= np.where(j < k[None], d > s.margin, -d > s.margin).all(axis=0)
                # the peak beyond both anchors and their surfaces continued to it
                tp = k - 1 - (fl - 1)  # the peak's beam offset from p
                rp = full[k, np.arange(c.size)]
                vl = V[-fl][c] + (V[-fl][c] - V[-fl - 1][c]) * (tp + fl)
                vr = V[fr][c] + (V[fr][c] - V[fr + 1][c]) * (fr - tp)
                cl = np.where(vl > 0, 1.0 / vl, np.inf)
                cr = np.where(vr > 0, 1.0 / vr, np.inf)
                keep &= (rp > np.fmax(cl, rl) + s.margin) & (rp > np.fmax(cr, rr) + s.margin)
                keep &= rp < np.fmax(rl, rr) + s.max_gap
                out[c[keep]] = True
    return out


def _thin_runs_hidden(
    R: dict[int, NDArray[np.float64]],
    V: dict[int, NDArray[np.float64]],
    C: dict[int, NDArray[np.float64]],
    r: NDArray[np.float64],
    s: GridSettings,
    step: float,
    step_x: float,
) -> NDArray[np.bool_]:
    """Runs of at most ``s.thin`` beams in front of a background surface on one side and
    cut on the other by a surface nearer than the run by more than ``max_gap`` (which no
    blend reaches), that recede into that cut: the run's beam next to it lies behind the
    run's nearest beam by more than the margin. The object's far edge then lies within
    the run, as it does between two backgrounds (``_thin_runs``): an object narrower than
    the run, whose every return blends it with the background hidden by the nearer one."""
    out = np.zeros(r.size, dtype=bool)
    top = s.reach + 2
    least = s.min_offset if s.min_offset > 0 else s.margin
    # per beam offset: a background behind p within max_gap; a surface nearer than p by
    # more than max_gap (the run's nearest beam is no farther than p)
    bg: dict[int, NDArray[np.bool_]] = {}
    cut: dict[int, NDArray[np.bool_]] = {}
    r_cut = r - s.max_gap
    with np.errstate(invalid="ignore", divide="ignore"):
        for L in range(2, s.thin + 1):
            for q in range(L):
                lo, hi = -(q + 1), L - q
                for b, o in ((lo, hi), (hi, lo)):
                    db, do = (1 if b > 0 else -1), (1 if o > 0 else -1)
                    if abs(b) + 2 > top or abs(o) > top:
                        continue
                    if b not in bg:
                        d = R[b] - r
                        bg[b] = (d > s.margin) & (d < s.max_gap)
                    if o not in cut:
                        cut[o] = R[o] < r_cut
                    c = np.flatnonzero(bg[b] & cut[o])
                    if c.size == 0:
                        continue
                    run = [R[m][c] for m in range(lo + 1, hi)]
                    near = np.minimum.reduce(run)
                    rb = R[b][c]
                    keep = R[o][c] < near - s.max_gap
                    # receding into the cut: the object ends within the run
                    keep &= R[o - do][c] > near + s.margin
                    # the background on a surface (its next two beams continue through it)
                    # and every beam of the run in front of it, continued across the run
                    keep &= _on_line(R, c, b, db, s, step)
                    vb, vb1 = V[b][c], V[b + db][c]
                    for m in range(lo + 1, hi):
                        v = vb + (vb - vb1) * abs(b - m)
                        cont = np.where(v > 0, 1.0 / v, np.inf)
                        keep &= (R[m][c] < rb - s.margin) & (R[m][c] < cont - s.margin)
                    # in front of the background across it too (grazing ground is no
                    # background a run stands in front of)
                    tan_a = r[c] * np.abs(vb - vb1) / step
                    tan_x = r[c] * C[b][c] / rb**2 / step_x
                    keep &= (rb - r[c]) / np.sqrt(1.0 + tan_a**2 + tan_x**2) > least
                    out[c[keep]] = True
    return out
