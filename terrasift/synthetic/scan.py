"""Synthetic ground-based (terrestrial) scans with exact mixed-measurement truth.

A sensor on a mast looks over a flat ground plane at boards and thin poles
3–15 m away, each with a wall 1–2.5 m behind it (the seed's test rigs, Tuley et
al. §III-B). Beams are cast on an azimuth/elevation grid. Every beam has a
footprint sampled by sub-rays; its intensity has two high lobes at the sides
and a weaker centre, like the SICK beam of the seed (§III-A.2). Per beam:

- one surface in the footprint: a return on the central ray at the mean range of
  the part on it;
- several surfaces closer than ``max_mix_gap`` to each other: one return on the
  central ray at the range weighted by the intercepted shares (share × lobe
  intensity) — a mixed measurement when that lands off every surface;
- surfaces farther apart: the nearest one with enough energy answers alone.

Truth per point is exact: a return farther than ``tol`` from every surface of
the scene whose beam blended several surfaces is MIXED, or GHOST when it comes
from a thin pole that sat in the weak centre of the beam (no lobe touched it),
so the return lies in the pole's range shadow (§III-C.3). A return off every
surface whose beam met one surface only (the rest of its footprint past an open
edge: nothing, or a background beyond ``max_mix_gap``) is EDGE: its range is the
part of the footprint on that surface, only its direction is the central ray's,
so it lies up to half a footprint past the edge. No second surface answered, so
it is no mixed measurement (the seed: a blend needs a foreground and a background
within 2.5 m); earlier versions counted it as MIXED (``is_off_surface``).
Everything else is CORRECT.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

CORRECT, MIXED, GHOST, EDGE = 0, 1, 2, 3


@dataclass(frozen=True)
class Board:
    """Vertical rectangle: centre (cx, cy), horizontal unit normal (nx, ny), z range."""

    cx: float
    cy: float
    nx: float
    ny: float
    half_width: float
    z0: float
    z1: float


@dataclass(frozen=True)
class Pole:
    """Vertical cylinder standing on the ground."""

    cx: float
    cy: float
    radius: float
    z1: float


@dataclass
class Scan:
    """One scan position: absolute points, the sensor origin and per-point truth."""

    xyz: NDArray[np.float64]
    truth: NDArray[np.uint8]
    origin: NDArray[np.float64]
    boards: list[Board] = field(default_factory=list)  # walls included, sensor-local frame
    poles: list[Pole] = field(default_factory=list)
    gps_time: NDArray[np.float64] | None = None  # seconds, one per return (scan order)

    @property
    def is_mixed(self) -> NDArray[np.bool_]:
        """Mixed or ghost: the returns a mixed-measurement filter should remove."""
        return (self.truth == MIXED) | (self.truth == GHOST)

    @property
    def is_off_surface(self) -> NDArray[np.bool_]:
        """Every return farther than ``tol`` from the scene: mixed, ghost and the edge
        returns of a footprint partly past an open edge (the earlier truth)."""
        return self.truth != CORRECT

    def __len__(self) -> int:
        return self.xyz.shape[0]


def make_scan(
    *,
    step_deg: float = 0.2,
    azimuth_deg: tuple[float, float] = (-60.0, 60.0),
    elevation_deg: tuple[float, float] = (-25.0, 10.0),
    mast_height: float = 1.5,
    beam_deg: tuple[float, float] = (0.25, 0.12),
    footprint_steps: float | None = None,
    sub_rays: tuple[int, int] = (11, 3),
    centre_intensity: float = 0.5,
    n_boards: int = 8,
    n_poles: int = 10,
    object_range: tuple[float, float] = (3.0, 15.0),
    wall_gap: tuple[float, float] = (1.0, 2.5),
    max_range: float | None = None,
    max_mix_gap: float = 2.5,
    min_share: float = 0.05,
    range_noise: float = 0.004,
    las_scale: float = 0.0,
    tol: float = 0.03,
    origin: tuple[float, float, float] = (500_000.0, 5_400_000.0, 100.0),
    seed: int = 0,
    chunk: int = 20_000,
    t0: float = 200_000.0,
    pulse_period: float = 2e-6,
    time_jitter: float = 0.02,
    scene: tuple[list[Board], list[Pole], list[Board]] | None = None,
    at: tuple[float, float] = (0.0, 0.0),
) -> Scan:
    """Ray-cast one scan of boards and poles in front of walls; see the module doc.

    ``beam_deg`` is the footprint (across, along the elevation), ``sub_rays`` its
    sampling; the outer half of the footprint across is the high-intensity lobes.
    ``footprint_steps`` instead gives a square footprint of that many angular steps
    (a mixed return then spreads as a ramp over about as many neighbouring beams).
    ``las_scale`` > 0 rounds the absolute coordinates to that step, as a LAS file
    stores them. ``max_range`` defaults to the farthest wall plus 5 m. Truth is
    taken on the noise-free returns, so it does not depend on noise or scale.
    ``gps_time`` follows the firing order (columns of azimuth, rows of elevation within
    each) from ``t0`` every ``pulse_period`` seconds, with a normal jitter of
    ``time_jitter`` periods; it is drawn from its own generator, so the points of a
    seed do not depend on it. ``scene`` (boards, poles, walls) replaces the drawn
    objects with given ones, placed in a frame where this sensor stands at ``at``.
    """
    rng = np.random.default_rng(seed)
    sensor = np.array([0.0, 0.0, mast_height])
    if scene is None:
        boards, poles, walls = _place_objects(
            rng, n_boards, n_poles, azimuth_deg, object_range, wall_gap
        )
    else:
        boards, poles, walls = _shift_scene(scene, at)
    planes = boards + walls
    if max_range is None:
        max_range = object_range[1] + wall_gap[1] + 5.0
    if footprint_steps is not None:
        beam_deg = (footprint_steps * step_deg, footprint_steps * step_deg)

    step = np.radians(step_deg)
    az = np.arange(np.radians(azimuth_deg[0]), np.radians(azimuth_deg[1]), step)
    el = np.arange(np.radians(elevation_deg[0]), np.radians(elevation_deg[1]), step)
    A, E = (g.ravel() for g in np.meshgrid(az, el, indexing="ij"))

    # Sub-ray offsets across (a) and along elevation (b); lobes at |a| >= 0.5.
    na, nb = sub_rays
    a = np.linspace(-1.0, 1.0, na)
    b = np.linspace(-1.0, 1.0, nb) if nb > 1 else np.zeros(1)
    ga, gb = (g.ravel() for g in np.meshgrid(a, b, indexing="ij"))
    intensity = np.where(np.abs(ga) >= 0.5, 1.0, centre_intensity)
    half_w, half_h = np.radians(beam_deg[0]) / 2, np.radians(beam_deg[1]) / 2
    pole_ids = np.arange(1 + len(planes), 1 + len(planes) + len(poles))

    # Chunks of beams keep the (beams, sub-rays, 3) arrays small.
    ranges = np.full(A.size, np.inf)
    ghost = np.zeros(A.size, dtype=bool)
    blend = np.zeros(A.size, dtype=bool)
    for c0 in range(0, A.size, chunk):
        sl = slice(c0, min(c0 + chunk, A.size))
        ranges[sl], ghost[sl], blend[sl] = _cast(
            A[sl],
            E[sl],
            ga,
            gb,
            intensity,
            half_w,
            half_h,
            sensor,
            mast_height,
            max_range,
            planes,
            poles,
            pole_ids,
            max_mix_gap,
            min_share,
        )
    ok = np.isfinite(ranges)
    centre = _direction(A[ok], E[ok])
    clean = sensor + centre * ranges[ok][:, None]
    pts = sensor + centre * (ranges[ok] + rng.normal(0.0, range_noise, ok.sum()))[:, None]
    ghost = ghost[ok]
    blend = blend[ok]

    dist = _distance_to_scene(clean, planes, poles)
    truth = np.full(pts.shape[0], CORRECT, dtype=np.uint8)
    off = dist > tol
    truth[off] = EDGE
    truth[off & blend] = MIXED
    truth[off & ghost] = GHOST
    shift = np.asarray(origin, dtype=np.float64)
    xyz = pts + shift
    if las_scale > 0:
        xyz = np.round(xyz / las_scale) * las_scale
    # A = azimuth column outer, E = elevation row inner: the beam number is the firing order
    beam = np.flatnonzero(ok).astype(np.float64)
    jitter = np.random.default_rng([seed, 1]).normal(0.0, time_jitter, beam.size)
    gps = t0 + (beam + jitter) * pulse_period
    return Scan(
        xyz=xyz,
        truth=truth,
        origin=sensor + shift,
        boards=planes,
        poles=poles,
        gps_time=gps,
    )


def _cast(
    A,
    E,
    ga,
    gb,
    intensity,
    half_w,
    half_h,
    sensor,
    mast_height,
    max_range,
    planes,
    poles,
    pole_ids,
    max_mix_gap,
    min_share,
):
    """Range, ghost flag and blend flag of each beam (azimuth A, elevation E)."""
    centre = _direction(A, E)
    e_az = np.stack([-np.sin(A), np.cos(A), np.zeros_like(A)], axis=1)
    e_el = np.stack([-np.sin(E) * np.cos(A), -np.sin(E) * np.sin(A), np.cos(E)], axis=1)
    dirs = (
        centre[:, None, :]
        + (ga * half_w)[None, :, None] * e_az[:, None, :]
        + (gb * half_h)[None, :, None] * e_el[:, None, :]
    )
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)  # (rays, sub, 3)

    # Nearest hit per sub-ray: id 0 ground, 1.. planes, then poles; -1 none.
    n_rays, n_sub = dirs.shape[:2]
    rng_hit = np.full((n_rays, n_sub), np.inf)
    hit_id = np.full((n_rays, n_sub), -1, dtype=np.int32)
    dz = dirs[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(dz < 0, -mast_height / dz, np.inf)
    take = t_ground < max_range
    rng_hit[take], hit_id[take] = t_ground[take], 0
    for k, obj in enumerate(planes + poles, start=1):
        rows = _candidate_rays(A, E, sensor, obj, half_w, half_h)
        if rows.size == 0:
            continue
        d = dirs[rows]
        t = _hit_board(sensor, d, obj) if isinstance(obj, Board) else _hit_pole(sensor, d, obj)
        closer = t < rng_hit[rows]
        sub_r = rng_hit[rows]
        sub_i = hit_id[rows]
        sub_r[closer], sub_i[closer] = t[closer], k
        rng_hit[rows], hit_id[rows] = sub_r, sub_i
    return _combine(rng_hit, hit_id, intensity, np.abs(ga) >= 0.5, pole_ids, max_mix_gap, min_share)


@dataclass
class ScanTile:
    """Several scan positions in one tile: points, truth, origins (k, 3) and each point's position."""

    xyz: NDArray[np.float64]
    truth: NDArray[np.uint8]
    origins: NDArray[np.float64]
    scan_id: NDArray[np.intp]
    gps_time: NDArray[np.float64] | None = None

    @property
    def is_mixed(self) -> NDArray[np.bool_]:
        return (self.truth == MIXED) | (self.truth == GHOST)

    @property
    def is_off_surface(self) -> NDArray[np.bool_]:
        return self.truth != CORRECT

    def __len__(self) -> int:
        return self.xyz.shape[0]


def make_scan_tile(
    positions: list[tuple[float, float, float]],
    *,
    ground: tuple[float, float, float] = (500_000.0, 5_400_000.0, 100.0),
    seed: int = 0,
    shared: bool = False,
    **scan_kw,
) -> ScanTile:
    """Scans from several positions (dx, dy, mast height) over one level ground.

    Each position ray-casts its own objects (a new draw per position), so per-point
    truth stays exact; positions share the ground plane at ``ground``'s height. With
    ``shared`` all positions scan one scene instead (drawn around the first position,
    each position's azimuth window turned to cover all its walls), so a return of one
    position may lie where another position's beams pass. The positions are scanned
    one after the other, an hour apart in GPS time.
    """
    t0 = float(scan_kw.pop("t0", 200_000.0))
    scene = None
    if shared:
        scene = _place_objects(
            np.random.default_rng([seed, 7]),
            scan_kw.get("n_boards", 8),
            scan_kw.get("n_poles", 10),
            scan_kw.get("azimuth_deg", (-60.0, 60.0)),
            scan_kw.get("object_range", (3.0, 15.0)),
            scan_kw.get("wall_gap", (1.0, 2.5)),
        )
    parts = []
    for k, (dx, dy, mast) in enumerate(positions):
        kw = dict(scan_kw)
        if scene is not None:
            at = (dx - positions[0][0], dy - positions[0][1])
            kw.update(scene=scene, at=at, azimuth_deg=_scene_azimuths(scene, at, 2.0))
        parts.append(
            make_scan(
                origin=(ground[0] + dx, ground[1] + dy, ground[2]),
                mast_height=mast,
                seed=seed * 1000 + k,
                t0=t0 + 3600.0 * k,
                **kw,
            )
        )
    return ScanTile(
        xyz=np.vstack([p.xyz for p in parts]),
        truth=np.concatenate([p.truth for p in parts]),
        origins=np.vstack([p.origin for p in parts]),
        scan_id=np.concatenate([np.full(len(p), k, dtype=np.intp) for k, p in enumerate(parts)]),
        gps_time=np.concatenate([p.gps_time for p in parts if p.gps_time is not None]),
    )


def _shift_scene(
    scene: tuple[list[Board], list[Pole], list[Board]], at: tuple[float, float]
) -> tuple[list[Board], list[Pole], list[Board]]:
    """The objects of ``scene`` seen from a sensor standing at ``at`` (x, y)."""
    bs, ps, ws = scene
    dx, dy = at

    def mv(b: Board) -> Board:
        return Board(b.cx - dx, b.cy - dy, b.nx, b.ny, b.half_width, b.z0, b.z1)

    return (
        [mv(b) for b in bs],
        [Pole(p.cx - dx, p.cy - dy, p.radius, p.z1) for p in ps],
        [mv(w) for w in ws],
    )


def _scene_azimuths(
    scene: tuple[list[Board], list[Pole], list[Board]], at: tuple[float, float], pad: float
) -> tuple[float, float]:
    """Azimuth window (degrees) over the ends of every wall of ``scene`` seen from ``at``."""
    ends = []
    for w in scene[2]:
        e = np.array([-w.ny, w.nx])
        for sgn in (-1.0, 1.0):
            ends.append(np.array([w.cx, w.cy]) + sgn * w.half_width * e - np.asarray(at))
    az = np.degrees(np.arctan2([v[1] for v in ends], [v[0] for v in ends]))
    return float(az.min() - pad), float(az.max() + pad)


def _direction(az: NDArray, el: NDArray) -> NDArray[np.float64]:
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


def _place_objects(rng, n_boards, n_poles, azimuth_deg, object_range, wall_gap):
    """Objects in separate azimuth sectors, each with its own wall behind it."""
    n = n_boards + n_poles
    kinds = rng.permutation(np.r_[np.zeros(n_boards, int), np.ones(n_poles, int)])
    edges = np.linspace(np.radians(azimuth_deg[0]), np.radians(azimuth_deg[1]), n + 1)
    boards: list[Board] = []
    poles: list[Pole] = []
    walls: list[Board] = []
    for i, kind in enumerate(kinds):
        lo, hi = edges[i], edges[i + 1]
        az = rng.uniform(lo + 0.3 * (hi - lo), hi - 0.3 * (hi - lo))
        dist = rng.uniform(*object_range)
        gap = rng.uniform(*wall_gap)
        c = np.array([np.cos(az), np.sin(az)])
        if kind == 0:
            yaw = np.radians(rng.uniform(-25, 25))
            nrm = -np.array([np.cos(az + yaw), np.sin(az + yaw)])
            half = min(rng.uniform(0.15, 0.5), 0.3 * (hi - lo) * dist)
            z0 = rng.choice([0.0, rng.uniform(0.2, 0.6)])
            boards.append(Board(*(c * dist), *nrm, half, z0, z0 + rng.uniform(0.4, 1.2)))
        else:
            poles.append(Pole(*(c * dist), rng.uniform(0.005, 0.04), rng.uniform(1.0, 2.5)))
        wd = dist + gap
        wall_half = 0.45 * (hi - lo) * wd
        wall_yaw = np.radians(rng.uniform(-15, 15))
        wn = -np.array([np.cos(az + wall_yaw), np.sin(az + wall_yaw)])
        walls.append(Board(*(c * wd), *wn, wall_half, 0.0, rng.uniform(1.5, 3.0)))
    return boards, poles, walls


def _candidate_rays(A, E, sensor, obj, half_w, half_h) -> NDArray[np.intp]:
    """Rays whose footprint may touch ``obj``: angular bounding box test."""
    if isinstance(obj, Board):
        e = np.array([-obj.ny, obj.nx])
        c = np.array([obj.cx, obj.cy])
        xy = np.array([c + s * obj.half_width * e for s in (-1, 1) for _ in (0, 1)])
        z = np.array([obj.z0, obj.z1, obj.z0, obj.z1])
        pad = 0.0
    else:
        xy = np.array([[obj.cx, obj.cy]] * 2)
        z = np.array([0.0, obj.z1])
        pad = np.arcsin(min(1.0, obj.radius / np.hypot(obj.cx, obj.cy)))
    rel = np.column_stack([xy, z]) - sensor
    az = np.arctan2(rel[:, 1], rel[:, 0])
    el = np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]))
    m = half_w / max(np.cos(el).min(), 0.2) + pad + 1e-6
    sel = (
        (az.min() - m <= A)
        & (az.max() + m >= A)
        & (el.min() - half_h - 1e-6 <= E)
        & (el.max() + half_h + 1e-6 >= E)
    )
    return np.flatnonzero(sel)


def _hit_board(s: NDArray, d: NDArray, b: Board) -> NDArray[np.float64]:
    n = np.array([b.nx, b.ny, 0.0])
    e = np.array([-b.ny, b.nx, 0.0])
    c = np.array([b.cx, b.cy, 0.0])
    dn = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c - s) @ n) / dn
    p = s + d * t[..., None]
    ok = (t > 0) & (np.abs((p - c) @ e) <= b.half_width) & (p[..., 2] >= b.z0) & (p[..., 2] <= b.z1)
    return np.where(ok, t, np.inf)


def _hit_pole(s: NDArray, d: NDArray, p: Pole) -> NDArray[np.float64]:
    ox, oy = s[0] - p.cx, s[1] - p.cy
    dx, dy = d[..., 0], d[..., 1]
    a = dx * dx + dy * dy
    bb = 2 * (ox * dx + oy * dy)
    cc = ox * ox + oy * oy - p.radius**2
    disc = bb * bb - 4 * a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-bb - np.sqrt(disc)) / (2 * a)
    z = s[2] + t * d[..., 2]
    ok = (disc >= 0) & (t > 0) & (z >= 0) & (z <= p.z1)
    return np.where(ok, t, np.inf)


def _combine(rng_hit, hit_id, intensity, lobe, pole_ids, max_mix_gap, min_share):
    """One range per beam from its sub-ray hits; also whether it is a ghost-type beam and
    whether it blended several surfaces (at least two with ``min_share`` within
    ``max_mix_gap``)."""
    n_rays = rng_hit.shape[0]
    hit = hit_id >= 0
    energy = np.where(hit, intensity[None, :], 0.0)
    total = energy.sum(axis=1)
    ranges = np.full(n_rays, np.inf)
    ids = np.unique(hit_id[hit])
    if ids.size == 0:
        return ranges, np.zeros(n_rays, dtype=bool), np.zeros(n_rays, dtype=bool)
    # Per beam and surface id: energy share and energy-weighted mean range.
    share = np.zeros((n_rays, ids.size))
    mean_r = np.full((n_rays, ids.size), np.inf)
    for j, k in enumerate(ids):
        m = hit_id == k
        ek = np.where(m, energy, 0.0)
        s = ek.sum(axis=1)
        has = s > 0
        share[has, j] = s[has] / total[has]
        mean_r[has, j] = (ek * np.where(m, rng_hit, 0.0)).sum(axis=1)[has] / s[has]
    strong = share >= min_share
    any_hit = total > 0
    near = np.where(strong, mean_r, np.inf).min(axis=1)
    far = np.where(strong, mean_r, -np.inf).max(axis=1)
    mixing = any_hit & (far - near <= max_mix_gap)
    w = np.where(strong, share, 0.0)
    wsum = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mix_r = (w * np.where(strong, mean_r, 0.0)).sum(axis=1) / wsum
    ranges[mixing] = mix_r[mixing]
    # Surfaces too far apart: the nearest strong one answers alone.
    alone = any_hit & ~mixing
    ranges[alone] = near[alone]
    # Ghost-type beams: a thin pole hit only by the weak centre of the beam.
    on_pole = np.isin(hit_id, pole_ids)
    ghost = on_pole.any(axis=1) & ~(on_pole & lobe[None, :]).any(axis=1)
    blend = mixing & (strong.sum(axis=1) >= 2)
    return ranges, ghost, blend


def _distance_to_scene(pts: NDArray, planes: list[Board], poles: list[Pole]) -> NDArray[np.float64]:
    dist = np.abs(pts[:, 2])
    for b in planes:
        e = np.array([-b.ny, b.nx])
        n = np.array([b.nx, b.ny])
        rel = pts[:, :2] - (b.cx, b.cy)
        ds = np.maximum(np.abs(rel @ e) - b.half_width, 0)
        dq = np.abs(rel @ n)
        dzz = np.maximum(np.maximum(b.z0 - pts[:, 2], pts[:, 2] - b.z1), 0)
        dist = np.minimum(dist, np.sqrt(ds**2 + dq**2 + dzz**2))
    for p in poles:
        rho = np.hypot(pts[:, 0] - p.cx, pts[:, 1] - p.cy)
        above = np.maximum(pts[:, 2] - p.z1, 0)
        dr = np.where(above > 0, np.maximum(rho - p.radius, 0), np.abs(rho - p.radius))
        dist = np.minimum(dist, np.hypot(dr, above))
    return dist
