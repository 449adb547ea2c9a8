"""Synthetic forests with a known bin class per bin, and analytic surfaces with exact gradients.

A forest is laid out on a bin grid. Each tree or bush owns a rectangle of whole
bins (its crown footprint), so every bin has one exact class: tree, bush, open
ground, or empty (a patch that returns nothing, like water under a steep look
angle). With ``round_crowns`` the crowns are discs inside their footprints and
a bin's truth is the crown under its centre; bins cut by a crown edge then
have no exact class, which the benchmark reports separately.

Pulses fall at uniform random positions. A pulse under a crown gives a first
return near the canopy top, sometimes a second inside the crown, and a ground
return when the beam gets through; elsewhere it hits the ground. Tree crowns
start at least 4 m above ground, so mowing at 3 m leaves only the bushes as
obstacles: the truth no-go bins are the bush bins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from rasterio.transform import Affine

from terrasift.synthetic.terrain import GROUND, Surface, _veg_class
from terrasift.workers.bins import Grid

EMPTY, OPEN, BUSH, TREE = 0, 1, 2, 3


@dataclass(frozen=True)
class AnalyticSurface:
    """z = z0 + gx·x + gy·y + Σ amp·sin(2π t / wavelength + phase), t along ``angle_deg``
    (counter-clockwise from east); ``gradient`` is exact."""

    z0: float = 100.0
    gx: float = 0.0
    gy: float = 0.0
    waves: tuple[tuple[float, float, float, float], ...] = ()  # (amp, wavelength, angle_deg, phase)

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        z = self.z0 + self.gx * x + self.gy * y
        for amp, wl, ang, ph in self.waves:
            a = np.radians(ang)
            z = z + amp * np.sin(2 * np.pi * (x * np.cos(a) + y * np.sin(a)) / wl + ph)
        return z

    def gradient(self, x: NDArray, y: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(∂z/∂x, ∂z/∂y) at each point."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        zx = np.full(np.broadcast(x, y).shape, self.gx)
        zy = np.full(zx.shape, self.gy)
        for amp, wl, ang, ph in self.waves:
            a = np.radians(ang)
            k = 2 * np.pi / wl
            d = amp * k * np.cos(k * (x * np.cos(a) + y * np.sin(a)) + ph)
            zx = zx + d * np.cos(a)
            zy = zy + d * np.sin(a)
        return zx, zy


def tilted_plane(gx: float = 0.12, gy: float = -0.07, z0: float = 100.0) -> AnalyticSurface:
    """A plane with gradient (gx, gy)."""
    return AnalyticSurface(z0, gx, gy)


def sinusoid(
    amp: float = 2.0,
    wavelength: float = 60.0,
    angle_deg: float = 30.0,
    gx: float = 0.02,
    gy: float = 0.0,
) -> AnalyticSurface:
    """Two crossing sinusoids on a gentle trend: slopes up to about 15°, curved in both axes."""
    return AnalyticSurface(
        100.0,
        gx,
        gy,
        ((amp, wavelength, angle_deg, 0.4), (0.6 * amp, 0.7 * wavelength, angle_deg + 100.0, 1.3)),
    )


def raster_of(
    surface: AnalyticSurface | Surface, x_left: float, y_top: float, cell: float, nx: int, ny: int
) -> tuple[NDArray[np.float64], Affine]:
    """The surface sampled at cell centres as a north-up DTM and its affine transform."""
    xs = x_left + (np.arange(nx) + 0.5) * cell
    ys = y_top - (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(xs, ys)
    return surface(gx, gy), Affine(cell, 0.0, x_left, 0.0, -cell, y_top)


@dataclass(frozen=True)
class Crown:
    """A tree or bush: footprint of whole bins from (ix, iy), w × h bins; heights above ground."""

    kind: int  # TREE or BUSH
    ix: int
    iy: int
    w: int
    h: int
    top: float
    base: float


@dataclass
class Forest:
    """Points with truth and the bin grid they were laid out on (absolute coordinates)."""

    xyz: NDArray[np.float64]
    truth: NDArray[np.uint8]  # ASPRS: 2 ground, 3/4/5 vegetation by height above ground
    height: NDArray[np.float64]  # true height above ground of each point (before noise)
    grid: Grid
    truth_class: NDArray[np.uint8]  # flat per bin: 0 empty, 1 open, 2 bush, 3 tree
    edge: NDArray[np.bool_]  # flat per bin: cut by a round crown's edge (never with square crowns)
    crowns: list[Crown]
    surface: Surface | AnalyticSurface = field(repr=False)

    @property
    def is_ground(self) -> NDArray[np.bool_]:
        return self.truth == GROUND

    @property
    def truth_nogo(self) -> NDArray[np.bool_]:
        """Obstacles below 3 m: the bush bins (tree crowns start at ≥ 4 m)."""
        return self.truth_class == BUSH

    def coverage(self) -> tuple[float, float]:
        """True (tree, bush) coverage over non-empty bins."""
        ne = self.truth_class != EMPTY
        return float((self.truth_class == TREE).sum() / ne.sum()), float(
            (self.truth_class == BUSH).sum() / ne.sum()
        )


def make_forest(
    size: float = 100.0,
    density: float = 30.0,
    cell: float = 1.0,
    *,
    origin: tuple[float, float] = (500_000.0, 5_400_000.0),
    surface: Surface | AnalyticSurface | None = None,
    tree_share: float = 0.3,
    bush_share: float = 0.1,
    empty_share: float = 0.03,
    round_crowns: bool = False,
    noise_sigma: float = 0.03,
    seed: int = 0,
) -> Forest:
    """A ``size`` × ``size`` m forest at ``density`` pulses per m² on a ``cell`` bin grid.

    Trees (tops 8–25 m, crowns from 4–8 m, 3–7 bins wide) and bushes (tops
    1–2.5 m, 2–4 bins wide) are placed without overlap until they cover about
    ``tree_share`` and ``bush_share`` of the bins; ``empty_share`` of the bins
    are no-return patches. The default ground is a gentle undulating surface
    (slopes below about 6°).
    """
    rng = np.random.default_rng(seed)
    surf = surface or Surface(
        z0=200.0, gx=0.03, gy=-0.02, waves=((1.0, 70.0, 20.0, 0.3), (0.5, 45.0, 110.0, 1.0))
    )
    nb = int(round(size / cell))
    owner = np.full((nb, nb), -1, dtype=np.int64)  # [iy, ix]: crown id, -2 empty patch
    crowns: list[Crown] = []

    def place(kind: int, share: float, sizes: tuple[int, int]) -> None:
        target = share * nb * nb
        area, tries = 0, 0
        while area < target and tries < 20_000:
            tries += 1
            w = int(rng.integers(sizes[0], sizes[1] + 1))
            h = w if round_crowns else int(rng.integers(sizes[0], sizes[1] + 1))
            ix, iy = int(rng.integers(0, nb - w + 1)), int(rng.integers(0, nb - h + 1))
            if (owner[iy : iy + h, ix : ix + w] != -1).any():
                continue
            if kind == TREE:
                top = rng.uniform(8.0, 25.0)
                base = rng.uniform(4.0, min(8.0, 0.5 * top))
            elif kind == BUSH:
                top, base = rng.uniform(1.0, 2.5), 0.0
            else:
                top = base = 0.0
            owner[iy : iy + h, ix : ix + w] = len(crowns) if kind != EMPTY else -2
            if kind != EMPTY:
                crowns.append(Crown(kind, ix, iy, w, h, top, base))
            area += w * h

    place(TREE, tree_share, (3, 7))
    place(BUSH, bush_share, (2, 4))
    place(EMPTY, empty_share, (2, 5))

    n_pulses = int(round(size * size * density))
    px, py = rng.uniform(0, nb * cell, n_pulses), rng.uniform(0, nb * cell, n_pulses)
    bx = np.minimum((px / cell).astype(np.int64), nb - 1)
    by = np.minimum((py / cell).astype(np.int64), nb - 1)
    who = owner[by, bx]
    keep = who != -2
    px, py, who = px[keep], py[keep], who[keep]

    # Canopy height of each pulse under its crown (−inf outside a round crown's disc).
    kinds = np.array([c.kind for c in crowns] + [OPEN])
    geo = np.array(
        [[c.ix, c.iy, c.w, c.h, c.top, c.base] for c in crowns] + [[0, 0, 1, 1, 0, 0]], float
    )
    g = geo[who]  # who == -1 picks the sentinel row
    cx, cy = (g[:, 0] + g[:, 2] / 2) * cell, (g[:, 1] + g[:, 3] / 2) * cell
    if round_crowns:
        r = np.hypot(px - cx, py - cy) / (g[:, 2] * cell / 2)
    else:
        r = np.maximum(
            np.abs(px - cx) / (g[:, 2] * cell / 2), np.abs(py - cy) / (g[:, 3] * cell / 2)
        )
    kind = kinds[who]
    canopy = np.where(
        kind == TREE,
        g[:, 5] + (g[:, 4] - g[:, 5]) * (1 - r**2),
        g[:, 4] * (1 - 0.5 * np.minimum(r, 1) ** 2),
    )
    under = (who >= 0) & (r <= 1)
    ground = surf(px, py)

    first = np.maximum(canopy - rng.exponential(0.3, px.size), 0.05)
    through = rng.random(px.size) < np.where(kind == TREE, 0.4, 0.25)
    mid = rng.random(px.size) < 0.35
    base = g[:, 5]
    mid_h = base + rng.random(px.size) * np.maximum(first - base, 0)

    sel_first, sel_mid, sel_ground = under, under & mid, ~under | through
    xs = np.concatenate([px[sel_first], px[sel_mid], px[sel_ground]])
    ys = np.concatenate([py[sel_first], py[sel_mid], py[sel_ground]])
    hs = np.concatenate([first[sel_first], mid_h[sel_mid], np.zeros(int(sel_ground.sum()))])
    zs = np.concatenate([ground[sel_first], ground[sel_mid], ground[sel_ground]]) + hs
    zs = zs + rng.normal(0, noise_sigma, zs.size)
    truth = np.where(hs > 0, _veg_class(hs), GROUND).astype(np.uint8)

    # Bin truth: the crown owning the bin, or for round crowns the crown under its centre.
    truth_class = np.full((nb, nb), OPEN, dtype=np.uint8)
    edge = np.zeros((nb, nb), dtype=bool)
    for c in crowns:
        sl = np.s_[c.iy : c.iy + c.h, c.ix : c.ix + c.w]
        if round_crowns:
            rad = c.w * cell / 2
            jj, ii = np.mgrid[0 : c.h, 0 : c.w]
            # distance from the crown centre to a bin's centre, nearest and farthest corner
            dx, dy = np.abs(ii + 0.5 - c.w / 2) * cell, np.abs(jj + 0.5 - c.h / 2) * cell
            centre_in = np.hypot(dx, dy) <= rad
            near = np.hypot(np.maximum(dx - cell / 2, 0), np.maximum(dy - cell / 2, 0))
            far = np.hypot(dx + cell / 2, dy + cell / 2)
            truth_class[sl] = np.where(centre_in, c.kind, OPEN)
            edge[sl] = (near < rad) & (far > rad)
        else:
            truth_class[sl] = c.kind
    truth_class[owner == -2] = EMPTY
    # A bin no pulse happened to hit holds no data, whatever stands on it.
    hits = np.bincount(
        np.minimum((ys / cell).astype(np.int64), nb - 1) * nb
        + np.minimum((xs / cell).astype(np.int64), nb - 1),
        minlength=nb * nb,
    )
    truth_class[hits.reshape(nb, nb) == 0] = EMPTY

    order = rng.permutation(xs.size)
    ox, oy = origin
    xyz = np.column_stack([xs[order] + ox, ys[order] + oy, zs[order]])
    grid = Grid(ox, oy, cell, nb, nb)

    def absolute(ax: NDArray, ay: NDArray) -> NDArray[np.float64]:
        return surf(np.asarray(ax) - ox, np.asarray(ay) - oy)

    return Forest(
        xyz=xyz,
        truth=truth[order],
        height=hs[order],
        grid=grid,
        truth_class=truth_class.ravel(),
        edge=edge.ravel(),
        crowns=crowns,
        surface=absolute,  # type: ignore[arg-type]
    )
