"""Synthetic airborne scenes with exact per-point truth and the true ground surface.

A scene is laid out as pulses at uniform random positions. Each pulse hits a
building roof (one return), or a tree/bush crown (first return in the crown,
sometimes a second inside it, and a last return on the ground when the beam
gets through), or bare ground. A small share of low outliers (multipath) and
high outliers (birds) is added as class 7. Truth classes follow ASPRS: 2 ground,
3/4/5 vegetation by height above ground (< 0.5, 0.5–2, > 2 m), 6 building, 7 noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

GROUND, LOW_VEG, MED_VEG, HIGH_VEG, BUILDING, NOISE = 2, 3, 4, 5, 6, 7


@dataclass(frozen=True)
class Surface:
    """z(x, y) = z0 + gx·x + gy·y + Σ sinusoids + Σ gaussian hills; exact and vectorised."""

    z0: float = 100.0
    gx: float = 0.05
    gy: float = -0.03
    waves: tuple[tuple[float, float, float, float], ...] = (
        (2.0, 180.0, 0.0, 0.3),
        (1.0, 70.0, 90.0, 1.1),
    )
    hills: tuple[tuple[float, float, float, float], ...] = ()  # (cx, cy, height, sigma)

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.z0 + self.gx * x + self.gy * y
        for amp, wavelength, angle_deg, phase in self.waves:
            a = np.radians(angle_deg)
            t = x * np.cos(a) + y * np.sin(a)
            z = z + amp * np.sin(2 * np.pi * t / wavelength + phase)
        for cx, cy, h, s in self.hills:
            z = z + h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        return z


@dataclass
class Scene:
    """Points with truth. ``surface`` gives the true ground height anywhere."""

    xyz: NDArray[np.float64]
    truth: NDArray[np.uint8]
    return_number: NDArray[np.uint8]
    number_of_returns: NDArray[np.uint8]
    surface: Callable[[NDArray, NDArray], NDArray]
    bounds: tuple[float, float, float, float]
    extra: dict[str, NDArray] = field(default_factory=dict)

    @property
    def is_ground(self) -> NDArray[np.bool_]:
        return self.truth == GROUND

    def __len__(self) -> int:
        return self.xyz.shape[0]


def make_scene(
    size: float = 200.0,
    density: float = 8.0,
    *,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
    surface: Surface | None = None,
    n_buildings: int = 6,
    building_size: tuple[float, float] = (10.0, 30.0),
    building_height: tuple[float, float] = (4.0, 15.0),
    tree_density: float = 0.004,
    bush_density: float = 0.004,
    outlier_rate: float = 0.001,
    noise_sigma: float = 0.03,
    seed: int = 0,
    height: float | None = None,
) -> Scene:
    """A square ``size`` × ``size`` m scene (``height`` for a rectangle) at
    ``density`` pulses per m², with buildings, trees, bushes and outliers.

    Tree and bush densities are stems per m². Coordinates are absolute (offset
    by ``origin``) so they look like a projected CRS; ``surface`` is evaluated
    on local coordinates and wrapped so callers pass absolute x, y.
    """
    rng = np.random.default_rng(seed)
    w, h = size, (height if height is not None else size)
    surf = surface or Surface()
    n_pulses = int(round(w * h * density))
    px = rng.uniform(0, w, n_pulses)
    py = rng.uniform(0, h, n_pulses)
    pulse_ground = surf(px, py)

    # Buildings: axis-aligned boxes with flat roofs, not overlapping each other much.
    in_building = np.zeros(n_pulses, dtype=bool)
    roof_z = np.zeros(n_pulses)
    for _ in range(n_buildings):
        bw, bh = rng.uniform(*building_size, 2)
        bx, by = rng.uniform(0.1 * w, 0.9 * w - bw), rng.uniform(0.1 * h, 0.9 * h - bh)
        inside = (px >= bx) & (px <= bx + bw) & (py >= by) & (py <= by + bh)
        base = surf(np.array([bx + bw / 2]), np.array([by + bh / 2]))[0]
        roof_z[inside] = base + rng.uniform(*building_height)
        in_building |= inside

    # Vegetation crowns: paraboloid tops; trees 6–25 m, bushes 0.8–2.5 m.
    n_trees = rng.poisson(tree_density * w * h)
    n_bushes = rng.poisson(bush_density * w * h)
    stems = np.column_stack(
        [rng.uniform(0, w, n_trees + n_bushes), rng.uniform(0, h, n_trees + n_bushes)]
    )
    top = np.r_[rng.uniform(6, 25, n_trees), rng.uniform(0.8, 2.5, n_bushes)]
    radius = np.r_[rng.uniform(2, 5, n_trees), rng.uniform(0.8, 2.0, n_bushes)]
    crown_base = np.r_[top[:n_trees] * rng.uniform(0.2, 0.5, n_trees), np.full(n_bushes, 0.2)]
    canopy = np.full(n_pulses, -np.inf)
    base_of_hit = np.zeros(n_pulses)
    if stems.shape[0]:
        tree = cKDTree(stems)
        # Up to 4 nearest stems: overlapping crowns take the highest canopy.
        k = min(4, stems.shape[0])
        dist, idx = tree.query(np.column_stack([px, py]), k=k)
        dist, idx = dist.reshape(n_pulses, k), idx.reshape(n_pulses, k)
        rel = dist / radius[idx]
        crown_h = np.where(
            rel < 1, crown_base[idx] + (top[idx] - crown_base[idx]) * (1 - rel**2), -np.inf
        )
        best = np.argmax(crown_h, axis=1)
        canopy = crown_h[np.arange(n_pulses), best]
        base_of_hit = crown_base[idx[np.arange(n_pulses), best]]
    in_crown = np.isfinite(canopy) & ~in_building

    xs, ys, zs, cls, rn, nr = [], [], [], [], [], []

    def emit(
        mask: NDArray, z: NDArray, c: NDArray | int, r: NDArray | int, n: NDArray | int
    ) -> None:
        xs.append(px[mask])
        ys.append(py[mask])
        zs.append(z)
        m = int(mask.sum())
        cls.append(np.broadcast_to(np.asarray(c, dtype=np.uint8), (m,)).copy())
        rn.append(np.broadcast_to(np.asarray(r, dtype=np.uint8), (m,)).copy())
        nr.append(np.broadcast_to(np.asarray(n, dtype=np.uint8), (m,)).copy())

    bare = ~in_building & ~in_crown
    emit(bare, pulse_ground[bare], GROUND, 1, 1)
    emit(in_building, roof_z[in_building], BUILDING, 1, 1)

    # Crown pulses: first return near the canopy top; maybe a second inside; maybe ground.
    ci = np.flatnonzero(in_crown)
    g = pulse_ground[ci]
    first_h = np.maximum(canopy[ci] - rng.exponential(0.3, ci.size), 0.05)
    has_mid = rng.random(ci.size) < 0.35
    mid_h = base_of_hit[ci] + rng.random(ci.size) * np.maximum(first_h - base_of_hit[ci], 0)
    has_ground = rng.random(ci.size) < np.where(top.max(initial=0) > 0, 0.45, 0.0)
    count = 1 + has_mid + has_ground
    sel = np.zeros(n_pulses, dtype=bool)
    sel[ci] = True
    emit(sel, g + first_h, _veg_class(first_h), 1, count)
    sel_mid = np.zeros(n_pulses, dtype=bool)
    sel_mid[ci[has_mid]] = True
    emit(sel_mid, g[has_mid] + mid_h[has_mid], _veg_class(mid_h[has_mid]), 2, count[has_mid])
    sel_g = np.zeros(n_pulses, dtype=bool)
    sel_g[ci[has_ground]] = True
    emit(sel_g, g[has_ground], GROUND, count[has_ground], count[has_ground])

    x = np.concatenate(xs)
    y = np.concatenate(ys)
    z = np.concatenate(zs) + rng.normal(0, noise_sigma, x.size)
    truth = np.concatenate(cls)
    ret = np.concatenate(rn)
    nret = np.concatenate(nr)

    n_out = rng.binomial(x.size, outlier_rate)
    if n_out:
        ox, oy = rng.uniform(0, w, n_out), rng.uniform(0, h, n_out)
        low = rng.random(n_out) < 0.7
        oz = surf(ox, oy) + np.where(low, -rng.uniform(1.0, 6.0, n_out), rng.uniform(40, 80, n_out))
        x, y, z = np.r_[x, ox], np.r_[y, oy], np.r_[z, oz]
        truth = np.r_[truth, np.full(n_out, NOISE, np.uint8)]
        ret = np.r_[ret, np.ones(n_out, np.uint8)]
        nret = np.r_[nret, np.ones(n_out, np.uint8)]

    return shuffled_scene(rng, (x, y, z), truth, ret, nret, surf, origin, (w, h))


def shuffled_scene(
    rng: np.random.Generator,
    xyz_local: tuple[NDArray, NDArray, NDArray],
    truth: NDArray[np.uint8],
    ret: NDArray[np.uint8],
    nret: NDArray[np.uint8],
    surf: Callable[[NDArray, NDArray], NDArray],
    origin: tuple[float, float],
    extent: tuple[float, float],
    extra: dict[str, NDArray] | None = None,
) -> Scene:
    """A Scene of points made in local coordinates: shuffled, so point order
    carries no hint of the class as in a real file (flight-line order is not
    class order), and moved to ``origin`` with the true surface moved along."""
    x, y, z = xyz_local
    order = rng.permutation(x.size)
    ox0, oy0 = origin
    xyz = np.column_stack([x[order] + ox0, y[order] + oy0, z[order]])

    def absolute_surface(ax: NDArray, ay: NDArray) -> NDArray[np.float64]:
        return surf(np.asarray(ax) - ox0, np.asarray(ay) - oy0)

    return Scene(
        xyz=xyz,
        truth=truth[order],
        return_number=ret[order],
        number_of_returns=nret[order],
        surface=absolute_surface,
        bounds=(ox0, oy0, ox0 + extent[0], oy0 + extent[1]),
        extra=extra or {},
    )


def _veg_class(height: NDArray) -> NDArray[np.uint8]:
    return np.where(height < 0.5, LOW_VEG, np.where(height < 2.0, MED_VEG, HIGH_VEG)).astype(
        np.uint8
    )


def write_las(
    scene: Scene,
    path: str | Path,
    *,
    crs: str | None = "EPSG:32632",
    point_format: int = 6,
    version: str = "1.4",
    scale: float = 0.01,
    classification: NDArray | None = None,
    extra_bytes: bool = False,
) -> Path:
    """Write ``scene`` as LAS or LAZ (by suffix). Classification is 1 unless given.

    With ``extra_bytes`` an extra dimension ``truth`` (uint8) carries the truth
    class, which also lets tests check extra bytes survive processing.
    """
    import laspy

    path = Path(path)
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([scale, scale, scale])
    header.offsets = np.floor(scene.xyz.min(axis=0))
    if extra_bytes:
        header.add_extra_dim(laspy.ExtraBytesParams(name="truth", type=np.uint8))
    if crs:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = scene.xyz[:, 0], scene.xyz[:, 1], scene.xyz[:, 2]
    las.return_number = scene.return_number
    las.number_of_returns = scene.number_of_returns
    las.classification = (
        classification if classification is not None else np.ones(len(scene), np.uint8)
    )
    las.intensity = np.arange(len(scene), dtype=np.uint64) % 65535
    if extra_bytes:
        las.truth = scene.truth
    las.write(str(path))
    return path


def write_tiles(
    scene: Scene, out_dir: str | Path, tile_size: float, *, suffix: str = ".laz"
) -> list[Path]:
    """Cut ``scene`` into square tiles of ``tile_size`` from its lower-left corner and
    write each as ``t<col>_<row><suffix>`` (a synthetic survey); returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    x0, y0 = scene.bounds[0], scene.bounds[1]
    col = np.floor((scene.xyz[:, 0] - x0) / tile_size).astype(np.int64)
    row = np.floor((scene.xyz[:, 1] - y0) / tile_size).astype(np.int64)
    paths = []
    for c, r in sorted({(int(a), int(b)) for a, b in zip(col, row, strict=True)}):
        m = (col == c) & (row == r)
        part = Scene(
            scene.xyz[m],
            scene.truth[m],
            scene.return_number[m],
            scene.number_of_returns[m],
            scene.surface,
            scene.bounds,
            {k: v[m] for k, v in scene.extra.items()},
        )
        paths.append(write_las(part, out / f"t{c}_{r}{suffix}"))
    return paths
