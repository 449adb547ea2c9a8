"""Scene families for ground filters after the scene types they lose on away from
the samples they were tuned on, each drawn from ranges by a seed, with exact truth.

- ``railway_yard``: level or gently sloping ground carrying long low flat
  objects 1–4 m high — rows of wagons on parallel tracks, parked rows of
  vehicles, long low sheds — and platforms (0.8–1.3 m high, vertical walls);
  a road embankment (ground, sloping sides) runs through some scenes;
- ``rural_slope``: mostly ground (70–95 % of the pulses), gentle (2–5 %) or
  steep (15–40 %) slopes, with low vegetation (shrubs 0.3–2.5 m, hedges along
  contour lines, scrub patches) and embankments, at 0.2–1 pulses per m², on
  ground with micro-relief (mounds, hollows, field banks: ``Relief``).

Objects are oriented rectangles with flat tops (truth class 6); vegetation
returns are class 3/4/5 by height above ground; embankments and cuttings
change the ground itself (their sides are ground). A pulse into low vegetation
returns somewhere between its top and half its height (returns under 0.25 m
count as ground: grass), or from the ground when it passes through a gap.
Echoes as a discrete-return sensor records them: where the vegetation return
stands higher above the ground than the scene's dead zone (the least
separation of two returns of one pulse: 0.6–3.5 m, log-uniform, drawn per
scene, as sensors differ), a share of those pulses (30–80 % per scene) goes on
to a second, last return from the ground (return 2 of 2, the first 1 of 2);
lower vegetation merges with the ground into one return (1 of 1). Scenes whose
dead zone is above their tallest vegetation carry single returns only (about
one in five). The echoes are drawn from a generator of their own (seeded by
the scene's seed), so the pulses, heights and truth of the single-return
scenes are those drawn before echoes were written. Each scene may lose a strip of data (a missing
flight-line overlap) and keeps ``make_scene``'s share of outliers (class 7).
Every length is drawn from the ranges in the docstrings; ``family(name, seed)``
draws one scene. ``Scene.extra["vegetation"]`` names what each point's pulse hit
first: ``SHRUB``, ``HEDGE`` or ``SCRUB`` (the plant a return came from, grass
included), else -1 (open ground, objects, outliers, last returns), so a score can
be split by what was taken as ground.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from terrasift.synthetic.terrain import BUILDING, GROUND, NOISE, Scene, Surface, _veg_class

ORIGIN = (500_000.0, 5_400_000.0)
GRASS = 0.25  # m: vegetation returns lower than this above the ground count as ground
DEAD_ZONE = (0.6, 3.5)  # m: least separation of two returns of a pulse, by sensor
THROUGH = (0.3, 0.8)  # share of pulses into vegetation above the dead zone reaching the ground
SHRUB, HEDGE, SCRUB = 0, 1, 2  # kinds of plant in Scene.extra["vegetation"]


@dataclass(frozen=True)
class Echoes:
    """How a scene's sensor records echoes: its own generator, the dead zone (m)
    and the share of pulses into vegetation above it that also return from the ground."""

    rng: np.random.Generator
    dead_zone: float
    through: float

    @classmethod
    def draw(cls, seed: int) -> Echoes:
        rng = np.random.default_rng([seed, 23])
        lo, hi = DEAD_ZONE
        dead = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        return cls(rng, dead, float(rng.uniform(*THROUGH)))


@dataclass(frozen=True)
class Box:
    """An oriented rectangle: centre, length along ``angle`` (radians), width, top height
    above the ground along its axis (level across, following the ground along its length)."""

    cx: float
    cy: float
    length: float
    width: float
    angle: float
    height: float

    def inside(self, x: NDArray, y: NDArray) -> NDArray[np.bool_]:
        c, s = np.cos(self.angle), np.sin(self.angle)
        u = (x - self.cx) * c + (y - self.cy) * s
        v = -(x - self.cx) * s + (y - self.cy) * c
        return (np.abs(u) <= self.length / 2) & (np.abs(v) <= self.width / 2)


@dataclass(frozen=True)
class Embankment:
    """A straight raised (``height`` > 0) or cut (< 0) strip of ground: crest ``top``
    wide, sides falling at ``side_slope`` (rise/run), along ``angle`` through (cx, cy)."""

    cx: float
    cy: float
    angle: float
    top: float
    height: float
    side_slope: float

    def lift(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        d = np.abs(-(x - self.cx) * np.sin(self.angle) + (y - self.cy) * np.cos(self.angle))
        run = abs(self.height) / self.side_slope
        return self.height * np.clip((self.top / 2 + run - d) / run, 0.0, 1.0)


@dataclass(frozen=True)
class Relief:
    """Micro-relief over a slope, as real rural ground has it between its breaks:
    mounds and hollows (rows: x, y, height (m, signed), sigma (m)), field banks
    along the contour (rows: x, y of a point on the bank, angle, height, run (m);
    a smooth step, convex at its shoulder and concave at its toe) and short waves
    (rows: amplitude, wavelength (m), angle, phase)."""

    mounds: NDArray[np.float64]
    banks: NDArray[np.float64]
    waves: NDArray[np.float64]

    @classmethod
    def draw(cls, seed: int, size: float, fall: float) -> Relief:
        """From a generator of its own (seeded by the scene's seed), so the pulses,
        vegetation and echoes of a scene are those drawn without relief: 4–12 mounds
        or hollows per hectare 0.2–0.8 m high (a third hollows), sigma 1.5–5 m; 0–3
        field banks 0.3–1 m high over a 1.5–5 m run, within 0.3 rad of the contour;
        two waves 0.05–0.25 m high, 8–30 m long."""
        rng = np.random.default_rng([seed, 31])
        n = int(rng.poisson(rng.uniform(4, 12) * size * size / 1e4))
        sign = np.where(rng.random(n) < 1 / 3, -1.0, 1.0)
        mounds = np.column_stack(
            [
                rng.uniform(0, size, (n, 2)),
                sign * rng.uniform(0.2, 0.8, n),
                rng.uniform(1.5, 5.0, n),
            ]
        )
        m = int(rng.integers(0, 4))
        banks = np.column_stack(
            [
                rng.uniform(0.1, 0.9, (m, 2)) * size,
                fall + np.pi / 2 + rng.uniform(-0.3, 0.3, m),
                rng.uniform(0.3, 1.0, m),
                rng.uniform(1.5, 5.0, m),
            ]
        )
        waves = np.column_stack(
            [
                rng.uniform(0.05, 0.25, 2),
                rng.uniform(8, 30, 2),
                rng.uniform(0, np.pi, 2),
                rng.uniform(0, 2 * np.pi, 2),
            ]
        )
        return cls(mounds, banks, waves)

    def lift(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        out = np.zeros(np.broadcast(x, y).shape)
        for cx, cy, h, s in self.mounds:
            out = out + h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        for bx, by, a, h, run in self.banks:
            # Signed distance across the bank; smoothstep from 0 (below) to h (above).
            t = np.clip(0.5 - (-(x - bx) * np.sin(a) + (y - by) * np.cos(a)) / run, 0.0, 1.0)
            out = out + h * t * t * (3 - 2 * t)
        for amp, length, a, phase in self.waves:
            out = out + amp * np.sin(2 * np.pi * (x * np.cos(a) + y * np.sin(a)) / length + phase)
        return out


def _ground_fn(
    surface: Surface, embankments: list[Embankment], relief: Relief | None = None
) -> Callable[[NDArray, NDArray], NDArray]:
    def z(x: NDArray, y: NDArray) -> NDArray[np.float64]:
        out = surface(x, y)
        for e in embankments:
            out = out + e.lift(x, y)
        if relief is not None:
            out = out + relief.lift(x, y)
        return out

    return z


def _assemble(
    rng: np.random.Generator,
    size: float,
    density: float,
    ground: Callable[[NDArray, NDArray], NDArray],
    boxes: list[Box],
    shrubs: NDArray[np.float64],
    noise_sigma: float,
    missing_strip: bool,
    echoes: Echoes | None = None,
    kinds: NDArray[np.int8] | None = None,
) -> Scene:
    """Pulses over ``size``² m at ``density``: box tops, shrub returns (rows of
    ``shrubs``: x, y, radius, top height, gap fraction; ``kinds``: each row's kind of
    plant, ``SHRUB`` for all when none), else ground; plus outliers.
    With ``echoes``, pulses into vegetation higher than its dead zone may go on to
    a last return from the ground (module doc); without, every pulse returns once."""
    n = int(round(size * size * density))
    px, py = rng.uniform(0, size, n), rng.uniform(0, size, n)
    if missing_strip:
        # A strip 0.1–0.25 of the tile wide without data (no overlap between flight lines).
        w = rng.uniform(0.1, 0.25) * size
        a = rng.uniform(0, np.pi)
        d = -(px - size / 2) * np.sin(a) + (py - size / 2) * np.cos(a)
        keep = np.abs(d - rng.uniform(-0.3, 0.3) * size) > w / 2
        px, py = px[keep], py[keep]
        n = px.size
    gz = ground(px, py)
    z = gz.copy()
    cls = np.full(n, GROUND, dtype=np.uint8)
    roof = np.zeros(n, dtype=bool)
    plant = np.full(n, -1, dtype=np.int8)  # kind of plant a pulse's return came from
    second = np.zeros(0, dtype=np.int64)  # pulses with a last return from the ground
    for b in boxes:
        inside = b.inside(px, py) & ~roof
        # Level across, following the ground along its length (as platforms and tracks do).
        c, s = np.cos(b.angle), np.sin(b.angle)
        u = (px[inside] - b.cx) * c + (py[inside] - b.cy) * s
        z[inside] = ground(b.cx + u * c, b.cy + u * s) + b.height
        cls[inside] = BUILDING
        roof |= inside
    if shrubs.shape[0]:
        from scipy.spatial import cKDTree

        k = min(3, shrubs.shape[0])
        dist, idx = cKDTree(shrubs[:, :2]).query(np.column_stack([px, py]), k=k)
        dist, idx = dist.reshape(n, k), idx.reshape(n, k)
        rel = dist / shrubs[idx, 2]
        crown = np.where(rel < 1, shrubs[idx, 3] * np.sqrt(np.clip(1 - rel**4, 0, 1)), -np.inf)
        best = np.argmax(crown, axis=1)
        h = crown[np.arange(n), best]
        gap = shrubs[idx[np.arange(n), best], 4]
        hit = np.isfinite(h) & ~roof & (rng.random(n) >= gap)
        rh = h[hit] * rng.uniform(0.5, 1.0, np.count_nonzero(hit))
        z[hit] = gz[hit] + rh
        # Returns within GRASS of the ground are grass: no filter parts them from ground noise.
        cls[hit] = np.where(rh < GRASS, GROUND, _veg_class(rh))
        plant[hit] = SHRUB if kinds is None else kinds[idx[np.arange(n), best][hit]]
        if echoes is not None:
            # Vegetation returns more than the dead zone above the ground: the pulse
            # may go on to the ground, a second (last) return of the same pulse.
            tall = np.flatnonzero(hit)[rh > echoes.dead_zone]
            second = tall[echoes.rng.random(tall.size) < echoes.through]
    z = z + rng.normal(0, noise_sigma, n)
    n_out = rng.binomial(n, 0.001)
    if n_out:
        ox, oy = rng.uniform(0, size, n_out), rng.uniform(0, size, n_out)
        low = rng.random(n_out) < 0.7
        oz = ground(ox, oy) + np.where(low, -rng.uniform(1, 6, n_out), rng.uniform(40, 80, n_out))
        px, py, z = np.r_[px, ox], np.r_[py, oy], np.r_[z, oz]
        cls = np.r_[cls, np.full(n_out, NOISE, np.uint8)]
        plant = np.r_[plant, np.full(n_out, -1, np.int8)]
    order = rng.permutation(px.size)
    ox0, oy0 = ORIGIN
    xyz = np.column_stack([px[order] + ox0, py[order] + oy0, z[order]])
    cls, plant = cls[order], plant[order]
    ret = np.ones(px.size, dtype=np.uint8)
    nret = np.ones(px.size, dtype=np.uint8)

    def absolute(ax: NDArray, ay: NDArray) -> NDArray[np.float64]:
        return ground(np.asarray(ax) - ox0, np.asarray(ay) - oy0)

    bounds = (ox0, oy0, ox0 + size, oy0 + size)
    if echoes is None or second.size == 0:
        return Scene(xyz, cls, ret, nret, absolute, bounds, {"vegetation": plant})
    # The first returns of the pulses that went on are 1 of 2; their last returns
    # (on the ground, with the scene's noise) 2 of 2, mixed into the order.
    where = np.empty(order.size, dtype=np.int64)
    where[order] = np.arange(order.size)
    first = where[second]
    nret[first] = 2
    sx, sy = px[second], py[second]
    sz = gz[second] + echoes.rng.normal(0, noise_sigma, second.size)
    xyz = np.concatenate([xyz, np.column_stack([sx + ox0, sy + oy0, sz])])
    cls = np.concatenate([cls, np.full(second.size, GROUND, np.uint8)])
    ret = np.concatenate([ret, np.full(second.size, 2, np.uint8)])
    nret = np.concatenate([nret, np.full(second.size, 2, np.uint8)])
    plant = np.concatenate([plant, np.full(second.size, -1, np.int8)])
    mix = echoes.rng.permutation(xyz.shape[0])
    return Scene(
        xyz[mix], cls[mix], ret[mix], nret[mix], absolute, bounds, {"vegetation": plant[mix]}
    )


def _terrain(rng: np.random.Generator, grade: float, size: float) -> Surface:
    """A plane of ``grade`` (rise/run) in a random direction with gentle undulation."""
    a = rng.uniform(0, 2 * np.pi)
    return Surface(
        z0=250.0,
        gx=grade * np.cos(a),
        gy=grade * np.sin(a),
        waves=((rng.uniform(0.2, 1.5), rng.uniform(0.6, 1.2) * size, rng.uniform(0, 180), 0.0),),
    )


def railway_yard(seed: int, size: float = 200.0, echoes: bool = True) -> Scene:
    """Level ground (grade 0–2 %) with 3–6 rows of low flat objects 1–4 m high:
    wagons 2.8–3.2 m wide and 12–25 m long, 1–1.5 m apart, on tracks 4.5–6 m apart;
    parked rows of cars (1.4–2 m, 4.5 × 1.8 m, 0.6–1 m apart); long low sheds (8–15 m wide,
    40–100 m long, 3–4 m high); platforms 4–8 m wide, 60–150 m long, 0.8–1.3 m high.
    0.5–4 pulses/m²; half the scenes have a road embankment 1–3 m high with sides at
    1:1.5–1:2 and a 6–10 m crest (ground). Orientation, counts and positions from ``seed``;
    ``echoes`` false: one return per pulse (the scene as drawn before echoes were written)."""
    rng = np.random.default_rng(seed)
    density = float(np.exp(rng.uniform(np.log(0.5), np.log(4.0))))
    surf = _terrain(rng, rng.uniform(0.0, 0.02), size)
    a = rng.uniform(0, np.pi)
    c, s = np.cos(a), np.sin(a)
    centre = np.array([size / 2, size / 2])
    along, across = np.array([c, s]), np.array([-s, c])
    boxes: list[Box] = []
    off = -0.4 * size
    kinds = rng.choice(["wagons", "wagons", "cars", "shed", "platform"], rng.integers(3, 7))
    for kind in kinds:
        if kind == "wagons":
            w, h, gap, step = rng.uniform(2.8, 3.2), rng.uniform(2.5, 4.0), rng.uniform(1, 1.5), 0.0
            lengths = (12.0, 25.0)
        elif kind == "cars":
            w, h, gap, step = 1.8, rng.uniform(1.4, 2.0), rng.uniform(0.6, 1.0), 0.0
            lengths = (4.5, 4.5)
        elif kind == "shed":
            w, h = rng.uniform(8, 15), rng.uniform(3, 4)
            gap, step, lengths = 0.0, 0.0, (40.0, 100.0)
        else:
            w, h = rng.uniform(4, 8), rng.uniform(0.8, 1.3)
            gap, step, lengths = 0.0, 0.0, (60.0, 150.0)
        row_len = rng.uniform(0.4, 0.9) * size
        start = rng.uniform(-0.45 * size, 0.45 * size - row_len)
        off += w / 2 + rng.uniform(4.5, 8.0)
        if off > 0.45 * size:
            break
        u = start
        while u < start + row_len:
            length = rng.uniform(*lengths)
            mid = centre + along * (u + length / 2) + across * off
            boxes.append(Box(mid[0], mid[1], length, w, a, h))
            u += length + (gap if kind in ("wagons", "cars") else row_len)
        off += w / 2 + step
    embankments = []
    if rng.random() < 0.5:
        b = a + np.pi / 2 + rng.uniform(-0.3, 0.3)
        p = centre + rng.uniform(-0.3, 0.3, 2) * size
        embankments.append(
            Embankment(
                p[0], p[1], b, rng.uniform(6, 10), rng.uniform(1, 3), 1 / rng.uniform(1.5, 2.0)
            )
        )
        # Nothing stands on the embankment: objects under its footprint go.
        boxes = [bx for bx in boxes if not _crosses(bx, embankments[0])]
    n_shrubs = rng.integers(0, 30)
    shrubs = np.column_stack(
        [
            rng.uniform(0, size, (n_shrubs, 2)),
            rng.uniform(0.8, 2.0, n_shrubs),
            rng.uniform(0.5, 2.0, n_shrubs),
            np.full(n_shrubs, 0.3),
        ]
    )
    shrubs = (
        shrubs[~np.any([bx.inside(shrubs[:, 0], shrubs[:, 1]) for bx in boxes], axis=0)]
        if (boxes and n_shrubs)
        else shrubs
    )
    return _assemble(
        rng,
        size,
        density,
        _ground_fn(surf, embankments),
        boxes,
        shrubs,
        rng.uniform(0.01, 0.05),
        rng.random() < 0.3,
        Echoes.draw(seed) if echoes else None,
    )


def _crosses(b: Box, e: Embankment) -> bool:
    """Whether any part of ``b`` (sampled every metre) lies on the embankment's footprint."""
    c, s = np.cos(b.angle), np.sin(b.angle)
    du, dv = np.meshgrid(
        np.linspace(-b.length / 2, b.length / 2, int(b.length) + 2),
        np.linspace(-b.width / 2, b.width / 2, int(b.width) + 2),
    )
    x = b.cx + du.ravel() * c - dv.ravel() * s
    y = b.cy + du.ravel() * s + dv.ravel() * c
    return bool(np.any(e.lift(x, y) != 0))


def rural_slope(seed: int, size: float = 200.0, echoes: bool = True, relief: bool = True) -> Scene:
    """Mostly ground: a slope of grade 2–5 % (gentle) or 15–40 % (steep, half the seeds)
    with low vegetation — 40–400 shrubs (radius 0.7–3 m, 0.3–2.5 m high, 10–50 % of
    pulses through to the ground), 1–4 hedges along the contour (2–4 m wide, 1–2.5 m
    high) and scrub patches — and 0–2 embankments or cuttings 0.5–3 m high with
    sides at 1:1–1:2. 0.2–1 pulses/m². ``echoes`` false: one return per pulse.
    ``relief`` (``Relief``): mounds, hollows, field banks and short waves on the
    ground, as real ground bends within metres; false: planar facets between the
    breaks (the scene as drawn before relief was added, same pulses)."""
    rng = np.random.default_rng(seed)
    density = float(np.exp(rng.uniform(np.log(0.2), np.log(1.0))))
    steep = seed % 2 == 1
    grade = rng.uniform(0.15, 0.40) if steep else rng.uniform(0.02, 0.05)
    surf = _terrain(rng, grade, size)
    fall = np.arctan2(surf.gy, surf.gx)
    shrubs, kinds = [], []
    n = int(rng.integers(40, 400))
    shrubs.append(
        np.column_stack(
            [
                rng.uniform(0, size, (n, 2)),
                rng.uniform(0.7, 3.0, n),
                rng.uniform(0.3, 2.5, n),
                rng.uniform(0.1, 0.5, n),
            ]
        )
    )
    kinds.append(np.full(n, SHRUB, np.int8))
    for _ in range(int(rng.integers(1, 5))):
        # A hedge along the contour: shrubs 2 m apart on a line across the fall line.
        p = rng.uniform(0.1, 0.9, 2) * size
        t = np.arange(-0.5 * size, 0.5 * size, 2.0)
        d = np.array([-np.sin(fall), np.cos(fall)])
        xy = p + t[:, None] * d
        xy = xy[(xy >= 0).all(1) & (xy <= size).all(1)]
        m = xy.shape[0]
        shrubs.append(
            np.column_stack(
                [
                    xy,
                    np.full(m, rng.uniform(1.0, 2.0)),
                    rng.uniform(1.0, 2.5, m),
                    np.full(m, rng.uniform(0.05, 0.3)),
                ]
            )
        )
        kinds.append(np.full(m, HEDGE, np.int8))
    for _ in range(int(rng.integers(0, 3))):
        # Scrub: a dense patch 15–40 m across of small shrubs.
        c = rng.uniform(0.1, 0.9, 2) * size
        r = rng.uniform(7.5, 20)
        m = int(r * r * 0.4)
        ang, rad = rng.uniform(0, 2 * np.pi, m), r * np.sqrt(rng.random(m))
        shrubs.append(
            np.column_stack(
                [
                    c[0] + rad * np.cos(ang),
                    c[1] + rad * np.sin(ang),
                    rng.uniform(0.7, 1.5, m),
                    rng.uniform(0.3, 1.5, m),
                    rng.uniform(0.1, 0.4, m),
                ]
            )
        )
        kinds.append(np.full(m, SCRUB, np.int8))
    embankments = []
    for _ in range(int(rng.integers(0, 3))):
        cx, cy = rng.uniform(0.2, 0.8, 2) * size  # drawn first, as before
        embankments.append(
            Embankment(
                float(cx),
                float(cy),
                rng.uniform(0, np.pi),
                rng.uniform(4, 10),
                rng.choice([-1, 1]) * rng.uniform(0.5, 3.0),
                1 / rng.uniform(1.0, 2.0),
            )
        )
    return _assemble(
        rng,
        size,
        density,
        _ground_fn(surf, embankments, Relief.draw(seed, size, fall) if relief else None),
        [],
        np.concatenate(shrubs),
        rng.uniform(0.01, 0.05),
        rng.random() < 0.3,
        Echoes.draw(seed) if echoes else None,
        np.concatenate(kinds),
    )


FAMILIES: dict[str, Callable[[int], Scene]] = {
    "railway_yard": railway_yard,
    "rural_slope": rural_slope,
}


def family(name: str, seed: int) -> Scene:
    """One scene of family ``name`` drawn by ``seed``."""
    return FAMILIES[name](seed)
