"""Synthetic airborne tiles of steep landforms and of a town, with exact truth.

The terrain is a height field on a fine raster (``cell``, 0.25 m by default):
a regional slope, a cliff band crossing the whole tile (so its face runs to
the tile's edges) with talus at its foot, free-standing mesas and buttes
(flat top, 60–90° faces, talus apron) and small steep hills (raised-cosine
domes). A town scene puts buildings on gentle ground instead: vertical walls,
flat or gabled roofs, no talus.

Pulses are cast as rays, not dropped vertically: each has a scan angle across
its flight line (uniform within ±``max_scan_angle``) and one of two flight
headings at right angles, and returns where it first meets the height field
(compiled ray march, ``_march``). So faces are sampled as the beam geometry
allows: densely by oblique beams, sparsely by near-vertical ones. Trees and
bushes stand on ground up to 40° steep, some of them at the foot of faces;
their crowns return as in ``terrasift.synthetic.terrain``.

Truth per point: ASPRS class (2 ground, 3/4/5 vegetation, 6 building, 7
noise) and, in ``Scene.extra``: ``face_angle`` (degrees, slope of the ground
at the point; NaN off ground), ``steep`` (ground steeper than 60°),
``landform`` (ground on a mesa, butte or hill: its top and flanks),
``near_face`` (vegetation within 5 m of ground steeper than 60°).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt, maximum_filter
from scipy.spatial import cKDTree

from terrasift.synthetic._kernels import _march
from terrasift.synthetic.terrain import BUILDING, GROUND, NOISE, Scene, _veg_class


@dataclass(frozen=True)
class Cliff:
    """A cliff band across the tile: face ``height`` m at ``angle``°, talus of
    ``talus`` m height at 33° at its foot, line through ``offset`` (share of the
    tile along the normal) facing ``facing``° (compass) and waving by ``wave`` m."""

    height: float = 30.0
    angle: float = 85.0
    talus: float = 6.0
    offset: float = 0.5
    facing: float = 200.0
    wave: float = 6.0


@dataclass(frozen=True)
class Mesa:
    """A mesa or butte: top ``radius`` m (lobed by 15 %), ``height`` m, faces at
    ``angle``°, talus apron up to ``talus`` × height at 33°."""

    x: float
    y: float
    radius: float
    height: float
    angle: float = 85.0
    talus: float = 0.25


@dataclass(frozen=True)
class Hill:
    """A raised-cosine hill: ``height`` m over ``radius`` m (max slope height·π/(2·radius))."""

    x: float
    y: float
    radius: float
    height: float


@dataclass(frozen=True)
class House:
    """A building: centre, size, heading (degrees), wall ``height`` and gable ``ridge`` (0 flat)."""

    x: float
    y: float
    width: float
    depth: float
    heading: float
    height: float
    ridge: float = 0.0


@dataclass
class LandformSpec:
    """Everything one tile holds; local coordinates 0 … ``size``."""

    size: float = 180.0
    density: float = 8.0
    slope: tuple[float, float] = (0.1, 0.05)
    cliffs: list[Cliff] = field(default_factory=list)
    mesas: list[Mesa] = field(default_factory=list)
    hills: list[Hill] = field(default_factory=list)
    houses: list[House] = field(default_factory=list)
    tree_density: float = 0.003
    bush_density: float = 0.004
    face_stems: int = 60
    """Trees and bushes placed 0.5–4 m from faces steeper than 60°."""
    max_scan_angle: float = 30.0
    heading: float = 0.0
    outlier_rate: float = 0.0005
    noise_sigma: float = 0.03
    cell: float = 0.25


def terrain_raster(spec: LandformSpec, margin: float) -> tuple[NDArray, NDArray, NDArray, float]:
    """Rock height field, object (building) height above it, landform mask, raster origin."""
    c = spec.cell
    lo = -margin
    n = int(np.ceil((spec.size + 2 * margin) / c)) + 1
    ax = lo + c * np.arange(n)
    x, y = np.meshgrid(ax, ax)
    z = 100.0 + spec.slope[0] * x + spec.slope[1] * y
    for cl in spec.cliffs:
        f = np.radians(cl.facing)
        nx, ny = np.sin(f), np.cos(f)  # outward normal of the face (downhill)
        along = -ny * x + nx * y
        s = -(
            (x - spec.size * 0.5) * nx
            + (y - spec.size * 0.5) * ny
            - (cl.offset - 0.5) * spec.size
            - cl.wave * np.sin(2 * np.pi * along / 90.0)
        )
        # s > 0 behind the face (up); talus below it, rising to the face's foot.
        talus_w = cl.talus / np.tan(np.radians(33.0))
        face_w = (cl.height - cl.talus) / np.tan(np.radians(cl.angle))
        rise = np.where(
            s < 0,
            cl.talus * np.clip(1 + s / talus_w, 0, 1),
            cl.talus + (cl.height - cl.talus) * np.clip(s / max(face_w, 1e-6), 0, 1),
        )
        z += rise
    land = np.zeros(z.shape, dtype=bool)
    for m in spec.mesas:
        dx, dy = x - m.x, y - m.y
        r = np.hypot(dx, dy)
        th = np.arctan2(dy, dx)
        rr = m.radius * (1 + 0.15 * np.sin(3 * th + m.x))
        t_h = m.talus * m.height
        face_w = (m.height - t_h) / np.tan(np.radians(m.angle))
        talus_w = t_h / np.tan(np.radians(33.0))
        d = r - rr
        up = np.where(
            d <= face_w,
            m.height - (m.height - t_h) * np.clip(d / max(face_w, 1e-6), 0, 1),
            t_h * np.clip(1 - (d - face_w) / talus_w, 0, 1),
        )
        z += up
        land |= d <= face_w + 1.0
    for h in spec.hills:
        r = np.hypot(x - h.x, y - h.y)
        z += np.where(r < h.radius, h.height * np.cos(0.5 * np.pi * r / h.radius) ** 2, 0.0)
        land |= r < 0.8 * h.radius
    obj = np.zeros_like(z)
    for b in spec.houses:
        a = np.radians(b.heading)
        u = (x - b.x) * np.cos(a) + (y - b.y) * np.sin(a)
        v = -(x - b.x) * np.sin(a) + (y - b.y) * np.cos(a)
        inside = (np.abs(u) <= b.width / 2) & (np.abs(v) <= b.depth / 2)
        roof = b.height + b.ridge * (1 - np.abs(v) / (b.depth / 2))
        base = float(100.0 + spec.slope[0] * b.x + spec.slope[1] * b.y)
        obj = np.where(inside, np.maximum(obj, base + roof - z), obj)
    return z, obj, land, lo


def make_landforms(
    spec: LandformSpec,
    *,
    seed: int = 0,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
) -> Scene:
    """One ``spec.size`` square tile at ``spec.density`` pulses per m²; see the module doc."""
    rng = np.random.default_rng(seed)
    s = spec.size
    margin = 30.0
    rock, obj, land, lo = terrain_raster(spec, margin)
    top = rock + obj
    c = spec.cell
    zmax = float(top.max()) + 2.0

    def at(a: NDArray, px: NDArray, py: NDArray) -> NDArray:
        i = np.clip(np.round((px - lo) / c).astype(int), 0, a.shape[1] - 1)
        j = np.clip(np.round((py - lo) / c).astype(int), 0, a.shape[0] - 1)
        return a[j, i]

    gy, gx = np.gradient(rock, c)
    slope_deg = np.degrees(np.arctan(np.hypot(gx, gy)))

    # Pulses aimed at uniform targets over the tile and a rim (rays leave obliquely).
    rim = 10.0
    n = int(round((s + 2 * rim) ** 2 * spec.density))
    tx = rng.uniform(-rim, s + rim, n)
    ty = rng.uniform(-rim, s + rim, n)
    theta = np.radians(rng.uniform(-spec.max_scan_angle, spec.max_scan_angle, n))
    head = np.radians(spec.heading + 90.0 * (rng.random(n) < 0.5))
    # Across track of a line flown along ``head`` (compass): (cos h, -sin h).
    d = np.column_stack(
        [np.sin(theta) * np.cos(head), -np.sin(theta) * np.sin(head), -np.cos(theta)]
    )
    tz = at(top, tx, ty)
    t0 = (zmax - tz) / np.cos(theta)
    start = np.column_stack([tx, ty, tz]) - t0[:, None] * d
    block = 16
    nb = int(np.ceil(top.shape[0] / block))
    padded = np.full((nb * block, nb * block), -np.inf)
    padded[: top.shape[0], : top.shape[1]] = top
    coarse = padded.reshape(nb, block, nb, block).max(axis=(1, 3))
    coarse = maximum_filter(coarse, size=3, mode="nearest")
    hit_t = _march(top, lo, c, start, d, 0.2, coarse, block)
    hit = start + hit_t[:, None] * d
    ok = np.isfinite(hit_t) & np.all((hit[:, :2] >= 0) & (hit[:, :2] <= s), axis=1)
    hit = hit[ok]
    m = hit.shape[0]
    hx, hy, hz = hit.T
    is_obj = at(obj, hx, hy) > 0.3
    angle = at(slope_deg, hx, hy)
    steep_cells = slope_deg > 60.0
    face_dist = distance_transform_edt(~steep_cells) * c

    # Stems: spread ones, and ones at the foot of faces; on ground under 40°, off roofs.
    n_spread = rng.poisson((spec.tree_density + spec.bush_density) * s * s)
    sx = list(rng.uniform(0, s, n_spread))
    sy = list(rng.uniform(0, s, n_spread))
    kind_tree = list(
        rng.random(n_spread) < spec.tree_density / max(spec.tree_density + spec.bush_density, 1e-12)
    )
    jj, ii = np.nonzero(steep_cells)
    if jj.size and spec.face_stems:
        pick = rng.integers(0, jj.size, 6 * spec.face_stems)
        off = rng.uniform(0.5, 4.0, pick.size)
        ang = rng.uniform(0, 2 * np.pi, pick.size)
        fx = lo + ii[pick] * c + off * np.cos(ang)
        fy = lo + jj[pick] * c + off * np.sin(ang)
        good = (
            (at(slope_deg, fx, fy) < 40.0)
            & (at(face_dist, fx, fy) > 0.4)
            & (fx >= 0)
            & (fx <= s)
            & (fy >= 0)
            & (fy <= s)
        )
        fx, fy = fx[good][: spec.face_stems], fy[good][: spec.face_stems]
        sx += list(fx)
        sy += list(fy)
        kind_tree += list(rng.random(fx.size) < 0.4)
    stem_x, stem_y = np.asarray(sx), np.asarray(sy)
    is_tree = np.asarray(kind_tree, dtype=bool)
    keep = (at(slope_deg, stem_x, stem_y) < 40.0) & (at(obj, stem_x, stem_y) <= 0.0)
    stem_x, stem_y, is_tree = stem_x[keep], stem_y[keep], is_tree[keep]
    k = stem_x.size
    tops = np.where(is_tree, rng.uniform(6, 20, k), rng.uniform(0.8, 2.5, k))
    radius = np.where(is_tree, rng.uniform(2, 4.5, k), rng.uniform(0.8, 2.0, k))
    cbase = np.where(is_tree, tops * rng.uniform(0.2, 0.5, k), 0.2)
    base_z = at(rock, stem_x, stem_y)

    in_crown = np.zeros(m, dtype=bool)
    canopy = np.zeros(m)
    crown_base = np.zeros(m)
    if k:
        kk = min(4, k)
        dist, idx = cKDTree(np.column_stack([stem_x, stem_y])).query(
            np.column_stack([hx, hy]), k=kk
        )
        dist, idx = dist.reshape(m, kk), idx.reshape(m, kk)
        rel = dist / radius[idx]
        ch = np.where(
            rel < 1, base_z[idx] + cbase[idx] + (tops[idx] - cbase[idx]) * (1 - rel**2), -np.inf
        )
        best = np.argmax(ch, axis=1)
        canopy = ch[np.arange(m), best]
        crown_base = base_z[idx[np.arange(m), best]] + cbase[idx[np.arange(m), best]]
        in_crown = np.isfinite(canopy) & (canopy > hz + 0.3) & ~is_obj

    parts: list[tuple] = []  # x, y, z, class, return, returns, angle
    bare = ~in_crown
    cls = np.where(is_obj, BUILDING, GROUND).astype(np.uint8)
    ang_g = np.where(is_obj, np.nan, angle)
    parts.append((hx[bare], hy[bare], hz[bare], cls[bare], 1, 1, ang_g[bare]))
    ci = np.flatnonzero(in_crown)
    g = hz[ci]
    first = np.maximum(canopy[ci] - rng.exponential(0.3, ci.size), g + 0.05)
    has_mid = rng.random(ci.size) < 0.35
    lowc = np.maximum(crown_base[ci], g)
    mid = lowc + rng.random(ci.size) * np.maximum(first - lowc, 0)
    has_ground = rng.random(ci.size) < 0.45
    count = (1 + has_mid + has_ground).astype(np.uint8)
    nan = np.full(ci.size, np.nan)
    parts.append((hx[ci], hy[ci], first, _veg_class(first - g), 1, count, nan))
    hm = has_mid
    parts.append(
        (hx[ci[hm]], hy[ci[hm]], mid[hm], _veg_class(mid[hm] - g[hm]), 2, count[hm], nan[hm])
    )
    hg = has_ground
    parts.append(
        (
            hx[ci[hg]],
            hy[ci[hg]],
            g[hg],
            np.full(hg.sum(), GROUND),
            count[hg],
            count[hg],
            angle[ci[hg]],
        )
    )

    def cat(i: int) -> NDArray:
        return np.concatenate([np.broadcast_to(np.asarray(p[i]), p[0].shape) for p in parts])

    x, y, z = cat(0), cat(1), cat(2)
    truth = cat(3).astype(np.uint8)
    ret, nret = cat(4).astype(np.uint8), cat(5).astype(np.uint8)
    face = cat(6).astype(np.float64)
    x = x + rng.normal(0, spec.noise_sigma, x.size)
    y = y + rng.normal(0, spec.noise_sigma, x.size)
    z = z + rng.normal(0, spec.noise_sigma, x.size)
    n_out = rng.binomial(x.size, spec.outlier_rate)
    if n_out:
        ox, oy = rng.uniform(0, s, n_out), rng.uniform(0, s, n_out)
        low = rng.random(n_out) < 0.7
        oz = np.where(
            low,
            at(rock, ox, oy) - rng.uniform(1, 6, n_out),
            at(top, ox, oy) + rng.uniform(40, 80, n_out),
        )
        x, y, z = np.r_[x, ox], np.r_[y, oy], np.r_[z, oz]
        truth = np.r_[truth, np.full(n_out, NOISE, np.uint8)]
        ret, nret = np.r_[ret, np.ones(n_out, np.uint8)], np.r_[nret, np.ones(n_out, np.uint8)]
        face = np.r_[face, np.full(n_out, np.nan)]
    order = rng.permutation(x.size)
    x, y, z, face = x[order], y[order], z[order], face[order]
    truth, ret, nret = truth[order], ret[order], nret[order]
    ground = truth == GROUND
    veg = (truth >= 3) & (truth <= 5)
    x0, y0 = float(origin[0]), float(origin[1])

    def surface(px: NDArray, py: NDArray) -> NDArray[np.float64]:
        return at(rock, np.asarray(px) - x0, np.asarray(py) - y0)

    return Scene(
        xyz=np.column_stack([x + x0, y + y0, z]),
        truth=truth,
        return_number=ret,
        number_of_returns=nret,
        surface=surface,
        bounds=(x0, y0, x0 + s, y0 + s),
        extra={
            "face_angle": face,
            "steep": ground & (np.nan_to_num(face) > 60.0),
            "landform": ground & at(land, x, y),
            "near_face": veg & (at(face_dist, x, y) < 5.0),
        },
    )
