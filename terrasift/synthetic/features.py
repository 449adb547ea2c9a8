"""A synthetic DTM with constructed terrain objects of known position and size.

The background is a hillside rising about 16 % to the north (so no tile of it
is flat and it holds no object by itself), with a gentle long wave, fine noise
and sparse low-vegetation bumps left in the DTM, plus a few nodata holes. On it:

- 3 ditches (two straight, one winding), trapezoidal, cut into the slope;
- 2 ridges (triangular, tapered ends); 3 round hills (cones);
- 2 ponds (a flat floor dug into the slope, banks blending into it);
- 2 roads along the contour (flat across, a few % grade along);
- a levelled field (the flat area).

Each object comes with its truth polygon (centreline buffered by its half
width, a circle, a square) and its length (centreline length, diameter or side).
Coordinates are absolute like a projected CRS (origin offset).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from rasterio import Affine
from scipy import ndimage
from shapely.geometry import LineString, Point, Polygon, box


@dataclass(frozen=True)
class TruthFeature:
    """One constructed object."""

    kind: str
    polygon: Polygon
    length_m: float


@dataclass
class FeatureScene:
    """The DTM (north-up, NaN nodata), its geotransform and the constructed objects."""

    dtm: NDArray[np.float64]
    transform: Affine
    cell: float
    truth: list[TruthFeature] = field(default_factory=list)

    def kinds(self) -> list[str]:
        return sorted({t.kind for t in self.truth})


def _distance_to_line(
    line: LineString, x: NDArray, y: NDArray, reach: float
) -> tuple[NDArray, NDArray, NDArray]:
    """Distance of points to a polyline, position along it (0..length) and a mask of points within ``reach``."""
    pts = np.asarray(line.coords)
    dist = np.full(x.shape, np.inf)
    along = np.zeros(x.shape)
    offset = 0.0
    for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:], strict=True):
        dx, dy = x1 - x0, y1 - y0
        seg_len = np.hypot(dx, dy)
        t = np.clip(((x - x0) * dx + (y - y0) * dy) / (seg_len * seg_len), 0, 1)
        d = np.hypot(x - (x0 + t * dx), y - (y0 + t * dy))
        better = d < dist
        dist[better] = d[better]
        along[better] = offset + t[better] * seg_len
        offset += seg_len
    return dist, along, dist <= reach


def _winding(
    start: tuple[float, float], end: tuple[float, float], amplitude: float, wavelength: float
) -> LineString:
    (x0, y0), (x1, y1) = start, end
    n = 200
    t = np.linspace(0, 1, n)
    length = np.hypot(x1 - x0, y1 - y0)
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    off = amplitude * np.sin(2 * np.pi * t * length / wavelength)
    return LineString(
        np.column_stack([x0 + t * (x1 - x0) - uy * off, y0 + t * (y1 - y0) + ux * off])
    )


def make_feature_scene(
    size: float = 640.0,
    cell: float = 0.5,
    *,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
    seed: int = 0,
    noise: float = 0.015,
    vegetation_share: float = 0.002,
    nodata_holes: int = 25,
    jitter: float = 8.0,
) -> FeatureScene:
    """The scene described in the module docstring, ``size`` m square.

    The layout is planned for 640 m and scaled to ``size``; every anchor point
    moves by up to ``jitter`` m and every radius by up to ±10 % at random
    (drawn again until objects keep 8 m apart), so seeds differ in layout as
    well as in noise.
    """
    for attempt in range(100):
        try:
            return _build(
                size, cell, origin, seed, attempt, noise, vegetation_share, nodata_holes, jitter
            )
        except _Overlap:
            continue
    raise RuntimeError("no layout with objects apart; lower jitter")


class _Overlap(Exception):
    pass


def _build(
    size: float,
    cell: float,
    origin: tuple[float, float],
    seed: int,
    attempt: int,
    noise: float,
    vegetation_share: float,
    nodata_holes: int,
    jitter: float,
) -> FeatureScene:
    rng = np.random.default_rng(seed)
    lay = np.random.default_rng([seed, attempt])
    n = int(round(size / cell))
    s = size / 640.0
    c = (np.arange(n) + 0.5) * cell
    x, y = np.meshgrid(c, size - c)  # row 0 is north
    gx, gy = 0.028, 0.158
    z = 100.0 + gx * x + gy * y + 1.0 * np.sin(2 * np.pi * (x + 0.3 * y) / (300.0 * s))
    truth: list[TruthFeature] = []

    def bg(px: float, py: float) -> float:
        return float(
            100.0 + gx * px + gy * py + 1.0 * np.sin(2 * np.pi * (px + 0.3 * py) / (300.0 * s))
        )

    def P(px: float, py: float) -> tuple[float, float]:
        dx, dy = lay.uniform(-jitter, jitter, 2)
        return px * s + dx, py * s + dy

    def R(r: float) -> float:
        return r * s * lay.uniform(0.9, 1.1)

    def win(geom_bounds: tuple[float, float, float, float], pad: float) -> tuple[slice, slice]:
        x0, y0, x1, y1 = geom_bounds
        c0, c1 = int(max(0, (x0 - pad) / cell)), int(min(n, (x1 + pad) / cell + 1))
        r0, r1 = int(max(0, (size - y1 - pad) / cell)), int(min(n, (size - y0 + pad) / cell + 1))
        return slice(r0, r1), slice(c0, c1)

    # --- flat area: a levelled square field, cut and filled into the slope over 8 m
    fx0, fy0, side = *P(40, 440), 110 * s
    fz = bg(fx0 + side / 2, fy0 + side / 2)
    ox = np.maximum(np.maximum(fx0 - x, x - (fx0 + side)), 0)
    oy = np.maximum(np.maximum(fy0 - y, y - (fy0 + side)), 0)
    out = np.hypot(ox, oy)
    w = np.clip(out / 12.0, 0, 1)
    w = w * w * (3 - 2 * w)
    z = fz + w * (z - fz)
    truth.append(TruthFeature("flat-area", box(fx0, fy0, fx0 + side, fy0 + side), side))

    # --- hills: cones, steep enough (≥ 0.35) that no flank levels out against the hillside
    for (hx, hy), radius, height in (
        (P(260, 500), R(22), 8.0),
        (P(400, 470), R(20), 7.5),
        (P(540, 420), R(24), 9.0),
    ):
        w_ = win((hx, hy, hx, hy), radius)
        r = np.hypot(x[w_] - hx, y[w_] - hy)
        zz = z[w_]
        inside = r < radius
        zz[inside] += height * (1 - r[inside] / radius)
        truth.append(TruthFeature("hill", Point(hx, hy).buffer(radius, 64), 2 * radius))

    # --- ridges: triangular cross-section (flanks 0.4), ends tapered over 25 m
    for a, b in ((P(330, 330), P(560, 290)), (P(575, 20), P(590, 175))):
        line = LineString([a, b])
        half, height = 15.0 * s, 6.0
        w_ = win(line.bounds, half)
        d, along, near = _distance_to_line(line, x[w_], y[w_], half)
        zz = z[w_]
        taper = np.clip(np.minimum(along, line.length - along) / 25.0, 0, 1)[near]
        zz[near] += height * taper * (1 - d[near] / half)
        truth.append(TruthFeature("ridge", line.buffer(half), line.length))

    # --- ponds: flat floor 2 m below the lowest point of the rim, banks over 5 m
    for (px, py), floor_r in ((P(110, 330), R(14)), (P(270, 370), R(11))):
        bank = 5.0
        w_ = win((px, py, px, py), floor_r + bank)
        r = np.hypot(x[w_] - px, y[w_] - py)
        zz = z[w_]
        ang = np.linspace(0, 2 * np.pi, 72, endpoint=False)
        rim = [
            bg(px + (floor_r + bank) * np.cos(t), py + (floor_r + bank) * np.sin(t)) for t in ang
        ]
        zf = min(rim) - 2.0
        t = np.clip((r - floor_r) / bank, 0, 1)
        sel = r < floor_r + bank
        zz[sel] = zf + t[sel] * (zz[sel] - zf)
        # the pond is its water surface: the flat floor inside the banks
        truth.append(TruthFeature("pond", Point(px, py).buffer(floor_r, 64), 2 * floor_r))

    # --- roads: 6 m flat across (height of the centreline), 3 m shoulders blending in
    for a, b in ((P(20, 610), P(620, 505)), (P(20, 200), P(620, 252))):
        line = LineString([a, b])
        half, shoulder = 3.0, 3.0
        w_ = win(line.bounds, half + shoulder)
        d, along, near = _distance_to_line(line, x[w_], y[w_], half + shoulder)
        zz = z[w_]
        ux, uy = (b[0] - a[0]) / line.length, (b[1] - a[1]) / line.length
        cx, cy = a[0] + along[near] * ux, a[1] + along[near] * uy
        zc = 100.0 + gx * cx + gy * cy + 1.0 * np.sin(2 * np.pi * (cx + 0.3 * cy) / (300.0 * s))
        t = np.clip((d[near] - half) / shoulder, 0, 1)
        zz[near] = zc + t * (zz[near] - zc)
        truth.append(TruthFeature("road", line.buffer(half), line.length))

    # --- ditches: trapezoid 1.2 m deep, 1 m bottom, 6 m across the top
    ditches = (
        LineString([P(40, 20), P(55, 180)]),
        LineString([P(120, 30), P(300, 170)]),
        _winding(P(340, 40), P(520, 150), 14.0 * s, 70.0 * s),
    )
    for line in ditches:
        depth, bottom, top = 1.2, 0.5, 3.0
        w_ = win(line.bounds, top)
        d, _, near = _distance_to_line(line, x[w_], y[w_], top)
        prof = np.clip((top - d[near]) / (top - bottom), 0, 1)
        z[w_][near] -= depth * prof
        truth.append(TruthFeature("ditch", line.buffer(top), line.length))

    _check_apart(truth)

    # --- measurement noise, low vegetation left in the DTM, nodata holes
    z += rng.normal(0, noise, z.shape)
    veg = rng.random(z.shape) < vegetation_share
    bumps = np.zeros_like(z)
    bumps[veg] = rng.uniform(0.05, 0.3, veg.sum())
    z += ndimage.grey_dilation(bumps, size=(2, 2)) if vegetation_share else 0
    for _ in range(nodata_holes):
        r0, c0 = rng.integers(0, n - 3, 2)
        hr, hc = rng.integers(1, 4, 2)
        z[r0 : r0 + hr, c0 : c0 + hc] = np.nan

    transform = Affine(cell, 0, origin[0], 0, -cell, origin[1] + size)
    shifted = [
        TruthFeature(t.kind, Polygon(_shift(t.polygon.exterior.coords, origin)), t.length_m)
        for t in truth
    ]
    return FeatureScene(z, transform, cell, shifted)


def _shift(coords, origin: tuple[float, float]) -> list[tuple[float, float]]:
    return [(px + origin[0], py + origin[1]) for px, py in coords]


def _check_apart(truth: list[TruthFeature], gap: float = 8.0) -> None:
    for i, a in enumerate(truth):
        for b in truth[i + 1 :]:
            if a.polygon.distance(b.polygon) < gap:
                raise _Overlap(f"{a.kind} and {b.kind} are closer than {gap} m")
