"""A family of terrain-object scenes drawn from ranges, with an exact surface.

Each scene is one background (level, gentle 2-5 % or sloped 8-15 %, in a
random direction, with a long low wave) carrying objects whose sizes are drawn
from the ranges below (ROBUSTNESS.md, *terrain objects*):

- hills: raised-cosine and triangular (cone) profiles, 15-60 m across;
- one ridge: raised-cosine or triangular cross-section 15-60 m across the
  base, 100-180 m long, ends tapered over half its width;
- two ditches: trapezoids 1-6 m across the top, 0.3-1.0 m deep, straight or
  winding, 60-200 m long;
- one pond: a flat floor 15-40 m across, 1-2 m below the lowest point of its
  rim, banks of 3-6 m;
- one or two straight roads 4-8 m wide whose flat top lies 0.2-1.5 m above
  (embankment) or below (cut) the ground at its centreline, side slopes
  1 : 1.5; on sloped ground they run along the contour (within 5 degrees);
- on sloped ground one levelled field, either 40-85 m or 120-170 m on a side,
  turned by up to 5 degrees (only the large ones are flat-area truth: a flat
  area is a square of at least 100 m).

The surface is an exact, vectorised function of local coordinates, so it can
be sampled by pulses (``point_scene``) or on a raster (``surface_raster``).
Hill and ridge heights are drawn so their steepest flanks rise at least 0.15
more than the background (else their uphill side is level ground by the
category definition, under 0.2 m per 2 m tile) and at most about 32 degrees.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from shapely.affinity import rotate
from shapely.geometry import LineString, Point, Polygon, box

from terrasift.synthetic.features import TruthFeature

BACKGROUNDS = ("level", "gentle", "sloped")


@dataclass
class FamilyScene:
    """One scene of the family: surface z(x, y) on local metres, truth in local metres."""

    seed: int
    size: float
    background: str
    slope: float
    noise: float
    density: float
    las_scale: float
    surface: Callable[[NDArray, NDArray], NDArray]
    truth: list[TruthFeature] = field(default_factory=list)
    info: list[str] = field(default_factory=list)

    def describe(self) -> str:
        return (
            f"seed {self.seed}: {self.background} {self.slope:.0%}, noise {self.noise * 100:.1f} cm, "
            f"{self.density:.1f} pulses/m2, LAS scale {self.las_scale:g}"
        )


def _segment_distance(
    x: NDArray, y: NDArray, pts: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Distance of points to a polyline and the position along it."""
    dist = np.full(x.shape, np.inf)
    along = np.zeros(x.shape)
    offset = 0.0
    for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:], strict=True):
        dx, dy = x1 - x0, y1 - y0
        seg = np.hypot(dx, dy)
        t = np.clip(((x - x0) * dx + (y - y0) * dy) / (seg * seg), 0, 1)
        d = np.hypot(x - (x0 + t * dx), y - (y0 + t * dy))
        better = d < dist
        dist[better] = d[better]
        along[better] = offset + t[better] * seg
        offset += seg
    return dist, along


def _profile(kind: str, u: NDArray) -> NDArray[np.float64]:
    """Unit bump of half-width 1: ``cosine`` (raised cosine) or ``triangle``; 0 beyond."""
    u = np.minimum(np.abs(u), 1.0)
    if kind == "cosine":
        return 0.5 * (1 + np.cos(np.pi * u))
    return 1 - u


class _Builder:
    """Collects object terms; each term adds to z inside its bounding box only."""

    def __init__(self, base: Callable[[NDArray, NDArray], NDArray]):
        self.base = base
        self.terms: list[tuple[tuple[float, float, float, float], Callable]] = []

    def add(self, bounds: tuple[float, float, float, float], fn: Callable) -> None:
        self.terms.append((bounds, fn))

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.base(x, y)
        for (x0, y0, x1, y1), fn in self.terms:
            sel = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            if sel.any():
                z[sel] = fn(x[sel], y[sel], z[sel])
        return z


def make_family_scene(seed: int, size: float = 320.0) -> FamilyScene:
    """Scene ``seed`` of the family (the background cycles level, gentle, sloped by seed)."""
    rng = np.random.default_rng([22, seed])
    background = BACKGROUNDS[seed % 3]
    slope = {"level": 0.0, "gentle": rng.uniform(0.02, 0.05), "sloped": rng.uniform(0.08, 0.15)}[
        background
    ]
    aspect = rng.uniform(0, 2 * np.pi)
    gx, gy = slope * np.cos(aspect), slope * np.sin(aspect)
    wave_amp = 0.1 if background == "level" else 0.5
    wave_len, wave_dir = rng.uniform(250, 400), rng.uniform(0, np.pi)

    def base(x: NDArray, y: NDArray) -> NDArray[np.float64]:
        t = x * np.cos(wave_dir) + y * np.sin(wave_dir)
        return 100.0 + gx * x + gy * y + wave_amp * np.sin(2 * np.pi * t / wave_len)

    noise = rng.uniform(0.01, 0.05)
    density = float(np.exp(rng.uniform(np.log(2), np.log(20))))
    las_scale = float(rng.choice([0.001, 0.01]))
    surf = _Builder(base)
    scene = FamilyScene(seed, size, background, slope, noise, density, las_scale, surf)
    placed: list[Polygon] = []  # footprints including blends, kept 10 m apart
    margin = 12.0

    def fits(footprint: Polygon) -> bool:
        inner = box(margin, margin, size - margin, size - margin)
        return inner.contains(footprint) and all(footprint.distance(p) >= 10 for p in placed)

    def attempt(make: Callable[[], tuple[Polygon, Callable[[], None]] | None]) -> bool:
        for _ in range(400):
            got = make()
            if got is None:
                continue
            footprint, commit = got
            if fits(footprint):
                placed.append(footprint)
                commit()
                return True
        return False

    def flank_ratio() -> tuple[float, float]:
        # height / width so the steepest flank (pi h / D cosine, 2 h / D triangle)
        # rises at least 0.15 more than the background (else the uphill side is
        # level ground: < 0.2 m per 2 m tile) and at most ~0.62 (32 deg)
        return max(0.08, (slope + 0.15) / 2), max(0.2, (slope + 0.15) / 2 + 0.02)

    # --- a levelled field on sloped ground
    if background == "sloped":
        large = bool(rng.random() < 0.6)

        def make_field():
            a, b = rng.uniform(120, 170, 2) if large else rng.uniform(40, 85, 2)
            turn = rng.uniform(-5, 5)
            cx, cy = rng.uniform(0, size, 2)
            poly = rotate(box(cx - a / 2, cy - b / 2, cx + a / 2, cy + b / 2), turn)
            zf = float(base(np.array([cx]), np.array([cy]))[0])
            cut = slope * np.hypot(a, b) / 2
            blend = max(8.0, 2.0 * cut)

            def commit():
                x0, y0, x1, y1 = poly.buffer(blend).bounds

                def fn(x, y, z, poly=poly, zf=zf, blend=blend):
                    from shapely import distance, points

                    d = distance(poly, points(x, y))
                    w = np.clip(d / blend, 0, 1)
                    w = w * w * (3 - 2 * w)
                    return zf + w * (z - zf)

                surf.add((x0, y0, x1, y1), fn)
                if large:
                    scene.truth.append(TruthFeature("flat-area", poly, float(max(a, b))))
                scene.info.append(f"field {a:.0f}x{b:.0f} m")

            return poly.buffer(blend), commit

        attempt(make_field)

    # --- roads (first: long)
    n_roads = int(rng.integers(1, 3))
    for _ in range(n_roads):
        width = rng.uniform(4, 8)
        offset = rng.uniform(0.2, 1.5) * rng.choice([-1, 1])
        length = rng.uniform(150, min(280, size - 2 * margin - 10))

        def make_road(width=width, offset=offset, length=length):
            if background == "sloped":
                ang = aspect + np.pi / 2 + np.radians(rng.uniform(-5, 5))
            else:
                ang = rng.uniform(0, np.pi)
            cx, cy = rng.uniform(0, size, 2)
            ux, uy = np.cos(ang), np.sin(ang)
            a = (cx - ux * length / 2, cy - uy * length / 2)
            b = (cx + ux * length / 2, cy + uy * length / 2)
            line = LineString([a, b])
            half = width / 2
            shoulder = 1.5 * (abs(offset) + slope * half) + 0.5
            reach = half + shoulder

            def commit():
                pts = np.asarray(line.coords)

                def fn(x, y, z, pts=pts, half=half, shoulder=shoulder, reach=reach):
                    d, along = _segment_distance(x, y, pts)
                    near = d <= reach
                    cx_ = pts[0, 0] + along * ux
                    cy_ = pts[0, 1] + along * uy
                    zr = base(cx_, cy_) + offset
                    t = np.clip((d - half) / shoulder, 0, 1)
                    return np.where(near, zr + t * (z - zr), z)

                surf.add(line.buffer(reach).bounds, fn)
                scene.truth.append(TruthFeature("road", line.buffer(half), float(line.length)))
                kind = "embankment" if offset > 0 else "cut"
                scene.info.append(f"road {width:.1f} m, {kind} {abs(offset):.2f} m")

            return line.buffer(reach), commit

        attempt(make_road)

    # --- one ridge
    ridge_w = rng.uniform(15, 60)
    ridge_len = rng.uniform(100, 180)
    prof = str(rng.choice(["cosine", "triangle"]))
    lo, hi = flank_ratio()
    ridge_h = ridge_w * rng.uniform(lo, hi)
    if prof == "triangle":
        ridge_h = min(ridge_h, ridge_w * 0.3)

    def make_ridge():
        ang = rng.uniform(0, np.pi)
        cx, cy = rng.uniform(0, size, 2)
        ux, uy = np.cos(ang), np.sin(ang)
        line = LineString(
            [
                (cx - ux * ridge_len / 2, cy - uy * ridge_len / 2),
                (cx + ux * ridge_len / 2, cy + uy * ridge_len / 2),
            ]
        )
        half = ridge_w / 2

        def commit():
            pts = np.asarray(line.coords)

            def fn(x, y, z, pts=pts):
                d, along = _segment_distance(x, y, pts)
                taper = np.clip(np.minimum(along, ridge_len - along) / half, 0, 1)
                return z + ridge_h * _profile(prof, d / half) * taper

            surf.add(line.buffer(half).bounds, fn)
            scene.truth.append(TruthFeature("ridge", line.buffer(half), float(ridge_len)))
            scene.info.append(f"ridge {prof} {ridge_w:.0f} m wide, {ridge_h:.1f} m high")

        return line.buffer(half), commit

    attempt(make_ridge)

    # --- hills: one of each profile
    for prof_h in ("cosine", "triangle"):
        diam = rng.uniform(15, 60)
        h = diam * rng.uniform(lo, hi)

        def make_hill(diam=diam, h=h, prof_h=prof_h):
            cx, cy = rng.uniform(0, size, 2)
            r = diam / 2

            def commit():
                def fn(x, y, z):
                    return z + h * _profile(prof_h, np.hypot(x - cx, y - cy) / r)

                surf.add((cx - r, cy - r, cx + r, cy + r), fn)
                scene.truth.append(TruthFeature("hill", Point(cx, cy).buffer(r, 64), float(diam)))
                scene.info.append(f"hill {prof_h} {diam:.0f} m, {h:.1f} m high")

            return Point(cx, cy).buffer(r), commit

        attempt(make_hill)

    # --- one pond
    floor = rng.uniform(15, 40)
    bank = rng.uniform(3, 6)
    depth = rng.uniform(1, 2)

    def make_pond():
        cx, cy = rng.uniform(0, size, 2)
        r = floor / 2

        def commit():
            ang = np.linspace(0, 2 * np.pi, 72, endpoint=False)
            rim = base(cx + (r + bank) * np.cos(ang), cy + (r + bank) * np.sin(ang))
            zf = float(rim.min() - depth)

            def fn(x, y, z):
                t = np.clip((np.hypot(x - cx, y - cy) - r) / bank, 0, 1)
                return np.where(t < 1, zf + t * (z - zf), z)

            surf.add((cx - r - bank, cy - r - bank, cx + r + bank, cy + r + bank), fn)
            scene.truth.append(TruthFeature("pond", Point(cx, cy).buffer(r, 64), float(floor)))
            scene.info.append(f"pond {floor:.0f} m, {depth:.1f} m deep")

        return Point(cx, cy).buffer(r + bank), commit

    attempt(make_pond)

    # --- two ditches
    for _ in range(2):
        top = rng.uniform(1, 6)
        ddepth = min(rng.uniform(0.3, 1.0), 0.25 + 0.3 * top)
        dlen = rng.uniform(60, 200)
        winding = bool(rng.random() < 0.4)

        def make_ditch(top=top, ddepth=ddepth, dlen=dlen, winding=winding):
            ang = rng.uniform(0, np.pi)
            cx, cy = rng.uniform(0, size, 2)
            ux, uy = np.cos(ang), np.sin(ang)
            t = np.linspace(-0.5, 0.5, 120)
            off = (
                rng.uniform(6, 12) * np.sin(2 * np.pi * t * dlen / rng.uniform(50, 90))
                if winding
                else np.zeros_like(t)
            )
            line = LineString(
                np.column_stack([cx + t * dlen * ux - uy * off, cy + t * dlen * uy + ux * off])
            )
            half = top / 2
            bottom = 0.3 * half

            def commit():
                pts = np.asarray(line.coords)

                def fn(x, y, z, pts=pts):
                    d, _ = _segment_distance(x, y, pts)
                    return z - ddepth * np.clip((half - d) / (half - bottom), 0, 1)

                surf.add(line.buffer(half).bounds, fn)
                scene.truth.append(TruthFeature("ditch", line.buffer(half), float(line.length)))
                shape = "winding" if winding else "straight"
                scene.info.append(f"ditch {shape} {top:.1f} m wide, {ddepth:.2f} m deep")

            return line.buffer(half), commit

        attempt(make_ditch)
    return scene


def make_sparse_scene(seed: int, size: float = 240.0) -> FamilyScene:
    """A counter-case scene with no terrain object: a field scanned sparsely.

    At 0.15-0.6 pulses/m^2 ground points lie 1.3-2.6 m apart, so the DTM is a
    TIN whose facets are as large as a category tile, and each facet's slope
    carries the points' 3-10 cm of noise. On a plain slope of 0-12 % (in a
    random direction, with a long low wave) tiles near the flatness threshold
    then read flat and not flat at random, and a strip of level tiles between
    two that are not flat looks like a road's cross-section. Truth: nothing
    (a flat-area detection is scored against the flat-area definition on the
    exact surface, as in the main family)."""
    rng = np.random.default_rng([2222, seed])
    slope = rng.uniform(0.0, 0.12)
    aspect = rng.uniform(0, 2 * np.pi)
    gx, gy = slope * np.cos(aspect), slope * np.sin(aspect)
    wave_amp, wave_len, wave_dir = (
        rng.uniform(0.1, 0.5),
        rng.uniform(250, 400),
        rng.uniform(0, np.pi),
    )

    def base(x: NDArray, y: NDArray) -> NDArray[np.float64]:
        t = x * np.cos(wave_dir) + y * np.sin(wave_dir)
        return 100.0 + gx * x + gy * y + wave_amp * np.sin(2 * np.pi * t / wave_len)

    noise = rng.uniform(0.03, 0.10)
    density = float(np.exp(rng.uniform(np.log(0.15), np.log(0.6))))
    las_scale = float(rng.choice([0.001, 0.01]))
    background = "level" if slope < 0.02 else "gentle" if slope < 0.05 else "sloped"
    return FamilyScene(
        seed, size, f"sparse {background}", slope, noise, density, las_scale, _Builder(base)
    )


def make_rough_scene(seed: int, size: float = 240.0) -> FamilyScene:
    """A counter-case scene with no terrain object: a rough, steep, hummocky slope.

    Drawn after ISPRS samp11 (a vegetated hillside), measured on its job DTM:
    regional slope 0.2-0.55 (median gradient over 24 m; 0.55 under the false
    ditch networks), hummocks whose DTM departs from its 6 m mean by 0.5-0.6 m
    RMS with an autocorrelation falling to one half at ~4.5 m, and 0.45-0.55
    ground points/m^2. Here: a plane of 15-55 % in a random direction plus a
    sum of 150 cosines with wavelengths 6-30 m in random directions (a smooth
    random field) of 0.15-0.6 m RMS, scanned at 0.3-3 pulses/m^2 with 2-8 cm
    of noise. Hollows between hummocks then have banks on both sides like a
    short ditch. Truth: nothing (a flat-area detection is scored against the
    flat-area definition on the exact surface, as in the main family)."""
    rng = np.random.default_rng([2223, seed])
    slope = rng.uniform(0.15, 0.55)
    aspect = rng.uniform(0, 2 * np.pi)
    gx, gy = slope * np.cos(aspect), slope * np.sin(aspect)
    n = 150
    wavelength = np.exp(rng.uniform(np.log(6.0), np.log(30.0), n))
    theta = rng.uniform(0, np.pi, n)
    kx, ky = 2 * np.pi * np.cos(theta) / wavelength, 2 * np.pi * np.sin(theta) / wavelength
    phase = rng.uniform(0, 2 * np.pi, n)
    rms = rng.uniform(0.3, 1.2)
    amp = rms * np.sqrt(2.0 / n)  # n cosines of equal amplitude a: RMS a sqrt(n / 2)

    def base(x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = 100.0 + gx * x + gy * y
        for i in range(n):
            z = z + amp * np.cos(kx[i] * x + ky[i] * y + phase[i])
        return z

    noise = rng.uniform(0.02, 0.08)
    density = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
    las_scale = float(rng.choice([0.001, 0.01]))
    scene = FamilyScene(seed, size, "rough", slope, noise, density, las_scale, _Builder(base))
    scene.info.append(f"hummocks {rms:.2f} m RMS")
    return scene


def surface_raster(scene: FamilyScene, cell: float = 0.5) -> NDArray[np.float64]:
    """The exact surface at the centres of a north-up ``cell`` grid over the scene (row 0 north)."""
    n = int(round(scene.size / cell))
    c = (np.arange(n) + 0.5) * cell
    x, y = np.meshgrid(c, scene.size - c)
    return scene.surface(x.ravel(), y.ravel()).reshape(n, n)


def point_scene(scene: FamilyScene, origin: tuple[float, float] = (500_000.0, 5_400_000.0)):
    """Pulses over the scene (terrasift.synthetic.terrain.make_scene): a few trees and bushes,
    no buildings, the family's noise and density, outliers."""
    from terrasift.synthetic.terrain import make_scene

    return make_scene(
        size=scene.size,
        density=scene.density,
        origin=origin,
        surface=scene.surface,  # type: ignore[arg-type]  # any z(x, y) callable works
        n_buildings=0,
        tree_density=0.0005,
        bush_density=0.0005,
        noise_sigma=scene.noise,
        seed=scene.seed,
    )
