"""Synthetic airborne scans of cliffs with exact truth (issue 4, DESIGN §5.3).

The rock surface is a cross-section polyline (u across strike, z up) extruded
along the strike v, then turned to ``azimuth``. Left to right it holds a lower
flat, talus rising to a vertical cliff, a plateau, an overhang whose lip juts
out over a terrace, a 70° face with talus at its foot, and a lower flat.

Pulses are cast as an oblique scanner casts them: each has a scan angle across
track (uniform within ±``max_scan_angle``, flight lines along the strike), and
its return is the first crossing of the ray with the polyline. So vertical faces
get points, the overhang's underside gets points from rays arriving from its
open side, and the terrace under the lip is partly in shadow. Trees and bushes
stand on the flats; their crowns return as in ``terrasift.synthetic.terrain``.

Truth per point: ASPRS class (2 ground, 3/4/5 vegetation, 7 noise) and, in
``Scene.extra``: ``face_angle`` (degrees between the ground's outward normal
and the vertical: 90 vertical, > 90 overhanging; NaN off ground), ``steep``
(ground on faces steeper than 60°) and ``covered`` (ground with rock above it
at the same x, y: the terrace under the lip). ``Scene.surface`` is the lowest
ground at x, y (the 2.5-D DTM).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.synthetic.terrain import GROUND, NOISE, Scene, _veg_class

#: (u, z) vertices of the default cross-section, metres
PROFILE: tuple[tuple[float, float], ...] = (
    (0.0, 0.0),
    (40.0, 0.5),  # lower flat, west
    (52.0, 8.0),  # talus, 32°
    (52.0, 30.0),  # vertical cliff, 22 m
    (104.0, 31.0),  # plateau up to the overhang's lip
    (100.0, 14.0),  # overhanging face, 103° (lip 4 m out over the terrace)
    (130.0, 14.5),  # terrace
    (134.0, 3.5),  # 70° face
    (142.0, 0.3),  # talus, 22°
    (220.0, 1.0),  # lower flat, east
)


def make_cliffs(
    length: float = 200.0,
    density: float = 8.0,
    *,
    profile: tuple[tuple[float, float], ...] = PROFILE,
    azimuth: float = 20.0,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
    max_scan_angle: float = 30.0,
    tree_density: float = 0.004,
    bush_density: float = 0.006,
    outlier_rate: float = 0.0005,
    noise_sigma: float = 0.03,
    seed: int = 0,
    square: float | None = None,
    face_clear: float = 2.0,
    veg_slope: float = 15.0,
) -> Scene:
    """A cliff scene ``profile``-wide across and ``length`` m along strike, at
    ``density`` pulses per m². ``azimuth`` (degrees, counter-clockwise from east)
    is the direction of increasing u, so the vertical cliff faces azimuth + 180°
    and the overhang and the 70° face face ``azimuth``. ``square``: keep only the
    axis-aligned square of that side about the scene's centre, as a block of
    the tiling grid would see it. ``face_clear``: metres between a crown's
    edge and the nearest steep (≥ 15°) segment's end (negative: crowns reach
    over the foot of faces); ``veg_slope``: degrees, the steepest ground that
    takes stems and crowns."""
    rng = np.random.default_rng(seed)
    prof = np.asarray(profile, dtype=np.float64)
    a, b = prof[:-1], prof[1:]
    width = float(prof[:, 0].max())
    n = int(round(width * length * density))

    # Rays in the (u, z) plane through a uniform target on z = 0.
    ut = rng.uniform(0.0, width, n)
    v = rng.uniform(0.0, length, n)
    theta = np.radians(rng.uniform(-max_scan_angle, max_scan_angle, n))
    d = np.column_stack([np.sin(theta), -np.cos(theta)])
    start = np.column_stack([ut, np.zeros(n)]) - 1000.0 * d
    hit_t, seg = _first_hit(start, d, a, b)
    # Rays leaving through the scene's sides hit nothing: drop them.
    ok = np.isfinite(hit_t)
    start, d, hit_t, seg, v = start[ok], d[ok], hit_t[ok], seg[ok], v[ok]
    hit = start + hit_t[:, None] * d
    u, zg = hit[:, 0], hit[:, 1]
    m = u.size

    e = b - a
    seg_angle = np.degrees(np.arccos(np.clip(e[:, 0] / np.hypot(e[:, 0], e[:, 1]), -1, 1)))
    angle = seg_angle[seg]
    covered = zg < _highest(prof, u) - 0.5

    # Vegetation on the flats, kept clear of steep segments by its crown radius.
    flat_ranges = [
        (min(p[0], q[0]), max(p[0], q[0]))
        for p, q, s in zip(a, b, seg_angle, strict=True)
        if s < veg_slope
    ]
    steep_u = np.concatenate(
        [[p[0], q[0]] for p, q, s in zip(a, b, seg_angle, strict=True) if s >= 15.0]
    )
    n_trees = rng.poisson(tree_density * width * length)
    n_bushes = rng.poisson(bush_density * width * length)
    k = n_trees + n_bushes
    top = np.r_[rng.uniform(6, 20, n_trees), rng.uniform(0.8, 2.5, n_bushes)]
    radius = np.r_[rng.uniform(2, 4.5, n_trees), rng.uniform(0.8, 2.0, n_bushes)]
    crown_base = np.r_[top[:n_trees] * rng.uniform(0.2, 0.5, n_trees), np.full(n_bushes, 0.2)]
    su = rng.uniform(0.0, width, 4 * k)
    sv = rng.uniform(0.0, length, 4 * k)
    clear = np.min(np.abs(su[:, None] - steep_u[None, :]), axis=1)
    on_flat = np.zeros(su.size, dtype=bool)
    for lo, hi in flat_ranges:
        on_flat |= (su >= lo) & (su <= hi)
    rr = np.resize(radius, su.size)
    good = np.flatnonzero(
        on_flat & (clear > rr + face_clear) & (_highest(prof, su) - _lowest(prof, su) < 0.5)
    )[:k]
    stems = np.column_stack([su[good], sv[good]])
    top, radius, crown_base = top[: good.size], radius[: good.size], crown_base[: good.size]
    # Crowns over open ground only: the ground under the overhang stays bare.
    canopy = np.full(m, -np.inf)
    base_of_hit = np.zeros(m)
    if stems.shape[0]:
        kk = min(4, stems.shape[0])
        dist, idx = cKDTree(stems).query(np.column_stack([u, v]), k=kk)
        dist, idx = dist.reshape(m, kk), idx.reshape(m, kk)
        rel = dist / radius[idx]
        crown_h = np.where(
            rel < 1, crown_base[idx] + (top[idx] - crown_base[idx]) * (1 - rel**2), -np.inf
        )
        best = np.argmax(crown_h, axis=1)
        canopy = crown_h[np.arange(m), best]
        base_of_hit = crown_base[idx[np.arange(m), best]]
    in_crown = np.isfinite(canopy) & (angle < veg_slope) & ~covered

    parts: list[tuple] = []  # (u, v, z, class, return, returns, angle, covered)
    bare = ~in_crown
    parts.append(
        (u[bare], v[bare], zg[bare], np.full(bare.sum(), GROUND), 1, 1, angle[bare], covered[bare])
    )
    ci = np.flatnonzero(in_crown)
    g = zg[ci]
    first_h = np.maximum(canopy[ci] - rng.exponential(0.3, ci.size), 0.05)
    has_mid = rng.random(ci.size) < 0.35
    mid_h = base_of_hit[ci] + rng.random(ci.size) * np.maximum(first_h - base_of_hit[ci], 0)
    has_ground = rng.random(ci.size) < 0.45
    count = (1 + has_mid + has_ground).astype(np.uint8)
    nan = np.full(ci.size, np.nan)
    no = np.zeros(ci.size, dtype=bool)
    parts.append((u[ci], v[ci], g + first_h, _veg_class(first_h), 1, count, nan, no))
    hm = has_mid
    parts.append(
        (
            u[ci[hm]],
            v[ci[hm]],
            g[hm] + mid_h[hm],
            _veg_class(mid_h[hm]),
            2,
            count[hm],
            nan[hm],
            no[hm],
        )
    )
    hg = has_ground
    parts.append(
        (
            u[ci[hg]],
            v[ci[hg]],
            g[hg],
            np.full(hg.sum(), GROUND),
            count[hg],
            count[hg],
            angle[ci[hg]],
            no[hg],
        )
    )

    def cat(i: int, dtype=None) -> NDArray:
        arrays = [np.broadcast_to(np.asarray(p[i]), p[0].shape) for p in parts]
        return np.concatenate(arrays).astype(dtype) if dtype else np.concatenate(arrays)

    uu, vv, zz = cat(0), cat(1), cat(2)
    truth = cat(3, np.uint8)
    ret, nret = cat(4, np.uint8), cat(5, np.uint8)
    face, cov = cat(6, np.float64), cat(7, bool)
    uu = uu + rng.normal(0, noise_sigma, uu.size)
    vv = vv + rng.normal(0, noise_sigma, uu.size)
    zz = zz + rng.normal(0, noise_sigma, uu.size)

    n_out = rng.binomial(uu.size, outlier_rate)
    if n_out:
        ou, ov = rng.uniform(0, width, n_out), rng.uniform(0, length, n_out)
        low = rng.random(n_out) < 0.7
        oz = np.where(
            low,
            _lowest(prof, ou) - rng.uniform(1.0, 6.0, n_out),
            _highest(prof, ou) + rng.uniform(40, 80, n_out),
        )
        uu, vv, zz = np.r_[uu, ou], np.r_[vv, ov], np.r_[zz, oz]
        truth = np.r_[truth, np.full(n_out, NOISE, np.uint8)]
        ret, nret = np.r_[ret, np.ones(n_out, np.uint8)], np.r_[nret, np.ones(n_out, np.uint8)]
        face, cov = np.r_[face, np.full(n_out, np.nan)], np.r_[cov, np.zeros(n_out, bool)]

    az = np.radians(azimuth)
    if square is not None:
        du, dv = uu - width / 2, vv - length / 2
        ex = du * np.cos(az) - dv * np.sin(az)
        ey = du * np.sin(az) + dv * np.cos(az)
        keep = (np.abs(ex) <= square / 2) & (np.abs(ey) <= square / 2)
        uu, vv, zz, truth, ret, nret, face, cov = (
            a[keep] for a in (uu, vv, zz, truth, ret, nret, face, cov)
        )
    order = rng.permutation(uu.size)
    cu, su_ = np.cos(az), np.sin(az)
    ox, oy = origin
    x = ox + uu * cu - vv * su_
    y = oy + uu * su_ + vv * cu
    xyz = np.column_stack([x, y, zz])[order]

    def surface(px: NDArray, py: NDArray) -> NDArray[np.float64]:
        dx, dy = np.asarray(px) - ox, np.asarray(py) - oy
        return _lowest(prof, dx * cu + dy * su_)

    corners_u = np.array([0.0, width, width, 0.0])
    corners_v = np.array([0.0, 0.0, length, length])
    cx = ox + corners_u * cu - corners_v * su_
    cy = oy + corners_u * su_ + corners_v * cu
    ground = truth[order] == GROUND
    face = face[order]
    return Scene(
        xyz=xyz,
        truth=truth[order],
        return_number=ret[order],
        number_of_returns=nret[order],
        surface=surface,
        bounds=(float(cx.min()), float(cy.min()), float(cx.max()), float(cy.max())),
        extra={
            "face_angle": face,
            "steep": ground & (np.nan_to_num(face) > 60.0),
            "covered": cov[order] & ground,
            "u": uu[order],
            "near_face": ((truth[order] >= 3) & (truth[order] <= 5))
            & (np.min(np.abs(uu[order][:, None] - steep_u[None, :]), axis=1) < 5.0),
        },
    )


def _first_hit(
    start: NDArray, d: NDArray, a: NDArray, b: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Ray parameter and segment index of each ray's first crossing (inf, -1 if none)."""
    e = b - a  # (S, 2)
    # start + t d = a + s e  ->  t d - s e = a - start
    det = d[:, None, 0] * (-e[None, :, 1]) - d[:, None, 1] * (-e[None, :, 0])
    w0 = a[None, :, 0] - start[:, None, 0]
    w1 = a[None, :, 1] - start[:, None, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w0 * (-e[None, :, 1]) - w1 * (-e[None, :, 0])) / det
        s = (d[:, None, 0] * w1 - d[:, None, 1] * w0) / det
    valid = (np.abs(det) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
    t = np.where(valid, t, np.inf)
    seg = np.argmin(t, axis=1)
    best = t[np.arange(t.shape[0]), seg]
    return best, np.where(np.isfinite(best), seg, -1)


def _heights(prof: NDArray, u: NDArray) -> NDArray[np.float64]:
    """Profile z of every non-vertical segment at each u (NaN where it does not span u)."""
    a, b = prof[:-1], prof[1:]
    lo, hi = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    span = hi - lo
    u = np.asarray(u, dtype=np.float64)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (u - a[:, 0]) / (b[:, 0] - a[:, 0])
    z = a[:, 1] + f * (b[:, 1] - a[:, 1])
    return np.where((span > 0) & (u >= lo) & (u <= hi), z, np.nan)


def _lowest(prof: NDArray, u: NDArray) -> NDArray[np.float64]:
    """The lowest ground at u: the 2.5-D terrain under any overhang."""
    return np.nanmin(_heights(prof, np.clip(u, prof[0, 0], prof[-1, 0])), axis=-1)


def _highest(prof: NDArray, u: NDArray) -> NDArray[np.float64]:
    return np.nanmax(_heights(prof, np.clip(u, prof[0, 0], prof[-1, 0])), axis=-1)
