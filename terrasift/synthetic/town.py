"""Synthetic towns with exact per-point truth: buildings, trees over roofs, walls, outliers.

A town is laid out as airborne pulses at uniform random positions over gentle
terrain. Buildings are rectangles at any angle, 5–100 m on a side, with a flat
roof (a slight drainage tilt) or a gable roof (15–45° pitch up to 20 m wide,
5–12° on wider halls; ridge along the long side). Trees stand anywhere, also beside buildings, so their crowns reach
over roofs. Each pulse gives its first return on the highest surface under it
(crown or roof or ground), sometimes a second inside a crown, and a last
return on what is under the crown (a roof or the ground) when the beam gets
through. Walls facing the scanner get returns from the look angle (an
off-nadir scan sees a band of wall ``height × tan θ`` wide), as do real
airborne scans. Isolated high (birds, 15–80 m up) and low (multipath, 1–6 m
down) outliers are added.

Truth follows ASPRS: 2 ground, 3/4/5 vegetation by height above ground
(< 0.5, 0.5–2, > 2 m), 6 building (roofs and walls, also under a crown),
7 noise. ``town_family`` draws the scenes of the building benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from terrasift.synthetic.terrain import (
    BUILDING,
    GROUND,
    NOISE,
    Scene,
    Surface,
    _veg_class,
    shuffled_scene,
)


@dataclass(frozen=True)
class House:
    """A rectangle ``length`` × ``width`` centred at (cx, cy), long side at ``angle``
    (radians, from east); eave ``eave`` m above the ground at the centre; gable
    roof of ``pitch`` degrees (0: flat, with a 1 % drainage tilt)."""

    cx: float
    cy: float
    length: float
    width: float
    angle: float
    base: float
    eave: float
    pitch: float

    def local(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        """Coordinates along (u) and across (v) the long side, from the centre."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        dx, dy = x - self.cx, y - self.cy
        return dx * c + dy * s, -dx * s + dy * c

    def inside(self, x: NDArray, y: NDArray) -> NDArray[np.bool_]:
        u, v = self.local(x, y)
        return (np.abs(u) <= self.length / 2) & (np.abs(v) <= self.width / 2)

    def roof(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Roof height at (x, y) (meaningful inside the footprint)."""
        u, v = self.local(x, y)
        top = self.base + self.eave
        if self.pitch <= 0:
            return top + 0.01 * u
        return top + np.tan(np.radians(self.pitch)) * (self.width / 2 - np.abs(v))


def make_town(
    size: float = 150.0,
    density: float = 4.0,
    *,
    seed: int = 0,
    n_buildings: int = 8,
    building_size: tuple[float, float] = (5.0, 100.0),
    pitched_share: float = 0.5,
    tree_density: float = 0.003,
    overhang_share: float = 0.5,
    look_angle_deg: float = 15.0,
    outlier_rate: float = 0.0005,
    noise_sigma: float = 0.03,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
    surface: Surface | None = None,
) -> Scene:
    """A ``size`` × ``size`` m town at ``density`` pulses per m².

    Building sides are drawn log-uniformly from ``building_size``; the first
    building takes the top of the range, so each scene has one large roof.
    ``overhang_share`` of the trees stand at a building's edge with a crown
    reaching over its roof and standing above it. ``look_angle_deg`` is the
    largest off-nadir angle of the scan (walls facing it are seen).
    """
    rng = np.random.default_rng(seed)
    surf = surface or Surface(
        z0=200.0, gx=0.02, gy=-0.01, waves=((1.0, 150.0, 30.0, 0.3), (0.5, 60.0, 120.0, 1.0))
    )
    houses = _place_houses(rng, size, n_buildings, building_size, pitched_share, surf)

    n_pulses = int(round(size * size * density))
    px, py = rng.uniform(0, size, n_pulses), rng.uniform(0, size, n_pulses)
    ground = surf(px, py)
    roof = np.full(n_pulses, -np.inf)
    for h in houses:
        inside = h.inside(px, py)
        roof[inside] = np.maximum(roof[inside], h.roof(px[inside], py[inside]))
    in_house = np.isfinite(roof)

    # Trees: some free-standing, some at a building edge reaching over its roof.
    n_trees = rng.poisson(tree_density * size * size)
    stems, tops, radii = [], [], []
    for _ in range(n_trees):
        radius = rng.uniform(2.0, 6.0)
        if houses and rng.random() < overhang_share:
            # Houses take trees by their perimeter: a small house gets a tree
            # over one side, not a roof wholly hidden.
            per = np.array([hh.length + hh.width for hh in houses])
            h = houses[rng.choice(len(houses), p=per / per.sum())]
            # A stem just outside a long side: the crown covers up to radius − gap of roof.
            side = rng.choice([-1.0, 1.0])
            u = rng.uniform(-h.length / 2, h.length / 2)
            v = side * (h.width / 2 + rng.uniform(0.5, 0.6 * radius))
            c, s = np.cos(h.angle), np.sin(h.angle)
            sx, sy = h.cx + u * c - v * s, h.cy + u * s + v * c
            roof_top = float(h.roof(np.array([h.cx]), np.array([h.cy]))[0]) - h.base
            top = roof_top + rng.uniform(2.0, 10.0)
        else:
            sx, sy = rng.uniform(0, size, 2)
            if any(h.inside(np.array([sx]), np.array([sy]))[0] for h in houses):
                continue
            top = rng.uniform(6.0, 25.0)
        stems.append((sx, sy))
        tops.append(top)
        radii.append(radius)
    canopy = np.full(n_pulses, -np.inf)
    crown_base = np.zeros(n_pulses)
    if stems:
        st = np.asarray(stems)
        top_a, rad_a = np.asarray(tops), np.asarray(radii)
        base_a = top_a * rng.uniform(0.3, 0.5, top_a.size)
        k = min(4, st.shape[0])
        dist, idx = cKDTree(st).query(np.column_stack([px, py]), k=k)
        dist, idx = dist.reshape(n_pulses, k), idx.reshape(n_pulses, k)
        rel = dist / rad_a[idx]
        gz = surf(st[:, 0], st[:, 1])
        h_abs = np.where(
            rel < 1,
            gz[idx] + base_a[idx] + (top_a[idx] - base_a[idx]) * (1 - rel**2),
            -np.inf,
        )
        best = np.argmax(h_abs, axis=1)
        rows = np.arange(n_pulses)
        canopy = h_abs[rows, best]
        crown_base = gz[idx[rows, best]] + base_a[idx[rows, best]]
    under = np.where(in_house, roof, ground)  # what a beam through a crown meets
    in_crown = np.isfinite(canopy) & (canopy > under + 0.5)

    xs: list[NDArray] = []
    ys: list[NDArray] = []
    zs: list[NDArray] = []
    cls: list[NDArray] = []
    rn: list[NDArray] = []
    nr: list[NDArray] = []

    def emit(sel: NDArray, z: NDArray, c: NDArray | int, r: NDArray | int, n: NDArray | int):
        m = int(sel.sum())
        xs.append(px[sel])
        ys.append(py[sel])
        zs.append(np.asarray(z, np.float64))
        for lst, v in ((cls, c), (rn, r), (nr, n)):
            lst.append(np.broadcast_to(np.asarray(v, np.uint8), (m,)).copy())

    open_ground = ~in_house & ~in_crown
    emit(open_ground, ground[open_ground], GROUND, 1, 1)
    bare_roof = in_house & ~in_crown
    emit(bare_roof, roof[bare_roof], BUILDING, 1, 1)

    ci = np.flatnonzero(in_crown)
    top_z = canopy[ci] - rng.exponential(0.3, ci.size)
    top_z = np.maximum(top_z, under[ci] + 0.3)
    has_mid = rng.random(ci.size) < 0.35
    lo = np.maximum(crown_base[ci], under[ci] + 0.3)
    mid_z = lo + rng.random(ci.size) * np.maximum(top_z - lo, 0)
    has_last = rng.random(ci.size) < 0.45
    count = 1 + has_mid + has_last
    g = ground[ci]
    sel = np.zeros(n_pulses, bool)
    sel[ci] = True
    emit(sel, top_z, _veg_class(top_z - g), 1, count)
    sel_mid = np.zeros(n_pulses, bool)
    sel_mid[ci[has_mid]] = True
    emit(sel_mid, mid_z[has_mid], _veg_class(mid_z[has_mid] - g[has_mid]), 2, count[has_mid])
    sel_last = np.zeros(n_pulses, bool)
    sel_last[ci[has_last]] = True
    last_cls = np.where(in_house[ci[has_last]], BUILDING, GROUND)
    emit(sel_last, under[ci[has_last]], last_cls, count[has_last], count[has_last])

    x, y, z = np.concatenate(xs), np.concatenate(ys), np.concatenate(zs)
    truth, ret, nret = np.concatenate(cls), np.concatenate(rn), np.concatenate(nr)

    # Walls facing the scanner: the look angle sweeps across x (0 at the
    # centre line), so a wall whose outward normal points toward the centre
    # line is seen over a band height × tan θ wide.
    wx, wy, wz = _wall_points(rng, houses, size, density, look_angle_deg, surf)
    x, y, z = np.r_[x, wx], np.r_[y, wy], np.r_[z, wz]
    truth = np.r_[truth, np.full(wx.size, BUILDING, np.uint8)]
    ret, nret = np.r_[ret, np.ones(wx.size, np.uint8)], np.r_[nret, np.ones(wx.size, np.uint8)]
    z = z + rng.normal(0, noise_sigma, z.size)

    n_out = rng.binomial(x.size, outlier_rate)
    if n_out:
        ox, oy = rng.uniform(0, size, n_out), rng.uniform(0, size, n_out)
        high = rng.random(n_out) < 0.5
        top_here = np.maximum(surf(ox, oy), _highest(houses, ox, oy))
        oz = np.where(
            high, top_here + rng.uniform(15, 80, n_out), surf(ox, oy) - rng.uniform(1, 6, n_out)
        )
        x, y, z = np.r_[x, ox], np.r_[y, oy], np.r_[z, oz]
        truth = np.r_[truth, np.full(n_out, NOISE, np.uint8)]
        ret, nret = np.r_[ret, np.ones(n_out, np.uint8)], np.r_[nret, np.ones(n_out, np.uint8)]

    return shuffled_scene(
        rng,
        (x, y, z),
        truth,
        ret,
        nret,
        surf,
        origin,
        (size, size),
        extra={"houses": np.array([h.length for h in houses])},
    )


def _highest(houses: list[House], x: NDArray, y: NDArray) -> NDArray[np.float64]:
    out = np.full(x.shape, -np.inf)
    for h in houses:
        inside = h.inside(x, y)
        out[inside] = np.maximum(out[inside], h.roof(x[inside], y[inside]))
    return out


def _place_houses(
    rng: np.random.Generator,
    size: float,
    n: int,
    sizes: tuple[float, float],
    pitched_share: float,
    surf: Surface,
) -> list[House]:
    """Non-overlapping houses (bounding circles 4 m apart), the first at the top of ``sizes``."""
    lo, hi = np.log(sizes[0]), np.log(sizes[1])
    houses: list[House] = []
    for attempt in range(200 * n):
        if len(houses) == n:
            break
        # The first house takes the top of the range, so each scene has a large roof.
        length = float(np.exp(rng.uniform(lo, hi))) if houses else min(sizes[1], 0.75 * size)
        width = max(sizes[0], length * rng.uniform(0.3, 1.0))
        if width > 0.4 * size:
            width = 0.4 * size
        r = 0.5 * np.hypot(length, width)
        margin = r + 2.0
        if 2 * margin >= size:
            continue
        cx, cy = rng.uniform(margin, size - margin, 2)
        if any(
            np.hypot(cx - h.cx, cy - h.cy) < r + 0.5 * np.hypot(h.length, h.width) + 4.0
            for h in houses
        ):
            continue
        # Houses have gable roofs of 15-45°; halls wider than 20 m low ones (5-12°),
        # as real roofs do (a 45° gable over 60 m would stand 30 m high).
        pitched = rng.random() < pitched_share
        pitch = 0.0
        if pitched:
            pitch = float(rng.uniform(15.0, 45.0) if width <= 20.0 else rng.uniform(5.0, 12.0))
        houses.append(
            House(
                cx=float(cx),
                cy=float(cy),
                length=length,
                width=width,
                angle=float(rng.uniform(0, np.pi)),
                base=float(surf(np.array([cx]), np.array([cy]))[0]),
                eave=float(rng.uniform(3.0, 15.0)),
                pitch=pitch,
            )
        )
        del attempt
    return houses


def _wall_points(
    rng: np.random.Generator,
    houses: list[House],
    size: float,
    density: float,
    look_angle_deg: float,
    surf: Surface,
) -> tuple[NDArray, NDArray, NDArray]:
    xs, ys, zs = [], [], []
    tan_max = np.tan(np.radians(look_angle_deg))
    for h in houses:
        c, s = np.cos(h.angle), np.sin(h.angle)
        eu, ev = np.array([c, s]), np.array([-s, c])  # along and across the long side
        centre = np.array([h.cx, h.cy])
        walls = [
            (sign * ev, centre + sign * h.width / 2 * ev, eu, h.length) for sign in (-1.0, 1.0)
        ] + [(sign * eu, centre + sign * h.length / 2 * eu, ev, h.width) for sign in (-1.0, 1.0)]
        eave = h.base + h.eave
        for normal, mid, along, span in walls:
            # The scanner flies over x = size / 2: the look angle grows toward
            # the edges, and a wall is seen when it faces the flight line.
            tan_here = tan_max * abs(mid[0] - size / 2) / (size / 2)
            facing = normal[0] * (size / 2 - mid[0]) > 0
            if not facing or tan_here <= 0:
                continue
            g = float(surf(mid[:1], mid[1:])[0])
            wall_h = max(eave - g, 0.0)
            # wall returns = pulses per m² × the ground band the wall hides
            m = rng.poisson(density * span * wall_h * tan_here * abs(normal[0]))
            if m == 0:
                continue
            t = rng.uniform(-span / 2, span / 2, m)
            zz = rng.uniform(g + 0.3, eave - 0.1, m)
            pos = mid + t[:, None] * along + 0.02 * normal
            xs.append(pos[:, 0])
            ys.append(pos[:, 1])
            zs.append(zz)
    if not xs:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(zs)


def town_family(
    seeds: range | list[int], densities: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0)
):
    """Scene arguments for the building benchmark: seed × density, with the
    pitched share, tree density and look angle drawn from ranges per seed."""
    out = []
    for seed in seeds:
        rng = np.random.default_rng(10_000 + seed)
        for density in densities:
            out.append(
                dict(
                    seed=seed,
                    density=density,
                    pitched_share=float(rng.uniform(0.2, 0.8)),
                    tree_density=float(rng.uniform(0.002, 0.006)),
                    overhang_share=float(rng.uniform(0.3, 0.7)),
                    look_angle_deg=float(rng.uniform(5.0, 20.0)),
                    noise_sigma=float(rng.uniform(0.01, 0.05)),
                )
            )
    return out
