"""Terrain categories on a tile grid over the DTM (Sjövall §1.4, DESIGN §5.7).

Each tile (default 2 m = 4 × 4 cells of a 0.5 m DTM) is fitted by one plane, or
by two planes meeting along an edge between two of its eight boundary points
when that fits clearly better. The one-plane fit is a fixed projection and
each of the 16 two-plane ("hinge") models adds one regressor |distance to the
edge line|, so its gain over the plane follows from one more projection
(Frisch–Waugh); a compiled pass (``_category_kernels.fit_tiles``) does this for
every tile, and measures its heights on every grid asked for, without stacking
the tiles into arrays. The result per tile:

- inclination 0–8: 0 none, else the direction (1 E, 2 NE, 3 N … 8 SE,
  counter-clockwise from east) the mean plane rises toward;
- orientation: the edge ``ab`` (a < b), an extreme point ``aa`` or 0;
- state: 0 one plane, 1 convex edge (ridge-like), 2 concave edge (ditch-like);
- height10: (max − min) inside the tile in decimetres;
- rise 0–8 (``Categories.rise``): the direction the plane rises toward, flat or not,
  where its gradient exceeds twice the slope noise (which way a flat tile slopes);
- grade (``Categories.grade``): the plane's gradient in whole multiples of the slope
  noise (how far the DTM supports that direction).

Noise. A DTM with a few centimetres of noise has tiles whose max − min is
noise rather than relief (16 cells of 4 cm noise span ~14 cm), so flatness is
judged on the fitted model where the model explains the tile up to the noise:
the noise σ is measured from the DTM itself (the median one-plane residual
of its tiles, corrected for the three fitted parameters, ``noise=None``), a
tile whose chosen model leaves a residual RMS within ``flat_noise`` σ is flat
when the model's own range is below ``flat_height``, others keep the raw
max − min (a bump or a pit the planes cannot follow); two planes are tried
only where the one-plane residual exceeds ``edge_noise`` σ too. With no noise
the model's range is the raw range and the test is the seed's.

Tiles with any nodata cell, and partial tiles at the right/bottom border, carry
``NODATA`` (255) in all four bands.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from rasterio import Affine

from terrasift.errors import ParameterError
from terrasift.workers._category_kernels import fit_tiles
from terrasift.workers._median_kernels import median_filter
from terrasift.workers.registry import StageParams, register

NODATA = 255

#: the sides of a tile; two boundary points on one side make no edge
_SIDES = ({8, 1, 2}, {2, 3, 4}, {4, 5, 6}, {6, 7, 8})

#: every edge between two boundary points on different sides (16 of them)
EDGES: tuple[int, ...] = tuple(
    10 * a + b
    for a in range(1, 9)
    for b in range(a + 1, 9)
    if not any(a in s and b in s for s in _SIDES)
)
#: extreme points; the category fit only produces the side midpoints (11, 33, 55, 77)
EXTREMES: tuple[int, ...] = tuple(11 * a for a in range(1, 9))
ORIENTATIONS: tuple[int, ...] = (0, *EDGES, *EXTREMES)


#: boundary points in tile units (tile spans [-1, 1]²), numbered as in DESIGN §5.7
_POINTS = {
    1: (1, 0),
    2: (1, 1),
    3: (0, 1),
    4: (-1, 1),
    5: (-1, 0),
    6: (-1, -1),
    7: (0, -1),
    8: (1, -1),
}


class CategoryParams(StageParams):
    """Parameters of the category fit."""

    presets = {"rough": {"flat_height": 0.3}}

    tile_size: float = Field(2.0, gt=0, le=50)
    """Tile side in metres, snapped to a whole number (≥ 2) of DTM cells."""
    flat_height: float = Field(0.2, ge=0, le=5)
    """A tile whose height (max − min) is below this is flat: all values 0. The seed's rough-forest variant uses 0.3."""
    incline_height: float = Field(0.15, ge=0, le=5)
    """Tiles with an edge get inclination 0 when their mean plane rises less than this across the tile (m)."""
    edge_min_rms: float = Field(0.03, ge=0, le=5)
    """A tile is considered for two planes only when the one-plane residual RMS exceeds this (m)."""
    edge_ratio: float = Field(0.35, gt=0, le=1)
    """Two planes are taken when their residual sum of squares is at most this share of one plane's."""
    extreme_ratio: float = Field(1.0, gt=0, le=10)
    """An E–W or N–S edge becomes an extreme point when the slope along it exceeds this times the slope across it."""
    noise: float | None = Field(None, ge=0, le=1)
    """DTM noise σ in metres; None measures it from the DTM (median one-plane residual of its tiles), 0 turns the noise tests off."""
    flat_noise: float = Field(2.0, ge=0, le=10)
    """A tile whose model leaves a residual RMS within this many σ is judged flat or not by the model's range."""
    edge_noise: float = Field(1.5, ge=0, le=10)
    """Two planes are tried only where the one-plane residual RMS exceeds this many σ (and edge_min_rms)."""
    slope_noise: float | None = Field(None, ge=0, le=1)
    """Noise σ of a tile's fitted slope (rise per metre); None measures it from the DTM
    (``measure_slope_noise``; 0 when ``noise`` is 0: the noise tests off), 0 turns the
    margin below off."""
    clear_slope_noise: float = Field(2.0, ge=0, le=10)
    """A tile is *clearly* not flat (``Categories.clear``, the filters' ``clear``) when its
    height exceeds ``flat_height`` by this many ``slope_noise`` times the tile's width
    between its outer cell centres: where the DTM is interpolated between points metres
    apart, its tiles' slopes carry the points' noise, and a slope near the threshold
    reads flat and not flat at random from tile to tile."""


#: fewest tiles with data for measuring the noise; below, it is taken as 0
MIN_NOISE_TILES = 64


@dataclass(frozen=True)
class Categories:
    """The four category bands on the tile grid, with the tile geometry."""

    inclination: NDArray[np.uint8]
    orientation: NDArray[np.uint8]
    state: NDArray[np.uint8]
    height10: NDArray[np.uint8]
    cells_per_tile: int
    tile_size: float
    noise: float = 0.0
    relief10: NDArray[np.uint8] | None = None
    """Height in decimetres as the flatness test sees it (the model's range where it
    explains the tile up to the noise, else max − min); the filters' ``height``."""
    step_cells: int | None = None
    """Cells between tile origins when tiles overlap (``step``); None: tiles abut."""
    lying10: NDArray[np.uint8] | None = None
    """``relief10`` of the tiles as they lie, before any regional slope is taken off
    (``trend``); the filters' ``lying-height``. None: as ``relief10``."""
    clear: NDArray[np.uint8] | None = None
    """1 where the tile is not flat by more than the slope noise explains
    (``CategoryParams.clear_slope_noise``), else 0; the filters' ``clear``. None: every
    tile that is not flat."""
    rise: NDArray[np.uint8] | None = None
    """Direction (1 E … 8 SE, as ``inclination``) the tile's plane rises toward, flat or
    not, where its gradient exceeds what the slope noise explains
    (``CategoryParams.clear_slope_noise`` σ_g), else 0; the filters' ``rise`` (which way
    a flat tile that is not level slopes). None: the filters take ``inclination``."""
    grade: NDArray[np.uint8] | None = None
    """The tile plane's gradient in whole multiples of the DTM's slope noise σ_g (0–254;
    254 for any gradient when σ_g is 0); the filters' ``grade`` (``grade not 0 1 2 3 4``:
    a slope the DTM's noise does not explain by five times over). None: the filters
    take 254 for tiles with an inclination, else 0."""
    flat_sigmas: float = math.inf
    """The flatness threshold in heights the slope noise σ_g gives across a tile
    (``flat_height`` / (σ_g × the tile's width between its outer cell centres)); inf when
    σ_g is 0. Where it is small, noise alone tips level tiles past the threshold; the
    filters' ``clear-share`` exemption reads it."""
    turned: NDArray[np.uint8] | None = None
    """Marks of a ``diagonal`` filter's segments searched on tiles turned by 45° and set
    back on this grid (bit 1 a turned row's, bit 2 a turned column's;
    ``features.turned``); ``categories_for`` makes them. None: no turned search."""

    @property
    def step(self) -> int:
        return self.step_cells or self.cells_per_tile

    @property
    def spacing(self) -> float:
        """Metres between neighbouring tiles of the grid (the tile size unless tiles overlap)."""
        return self.tile_size * self.step / self.cells_per_tile

    @property
    def shape(self) -> tuple[int, int]:
        return self.inclination.shape

    @property
    def nodata(self) -> NDArray[np.bool_]:
        return self.inclination == NODATA

    def transform(self, dtm_transform: Affine) -> Affine:
        """The tile grid's geotransform given the DTM's (overlapping tiles: a grid
        cell of one step centred on its tile)."""
        off = (self.cells_per_tile - self.step) / 2
        return dtm_transform @ Affine.translation(off, off) @ Affine.scale(self.step)

    def bands(self) -> NDArray[np.uint8]:
        """(4, rows, cols) uint8 in the order of ``categories.tif``."""
        return np.stack([self.inclination, self.orientation, self.state, self.height10])


@lru_cache(maxsize=8)
def _models(k: int, cell: float) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Projection and hinge regressors for k × k cell tiles (cell centres, metres, north-up)."""
    half = k * cell / 2
    c = (np.arange(k) + 0.5) * cell - half
    xx, yy = np.meshgrid(c, -c)  # row 0 is north
    x, y = xx.ravel(), yy.ravel()
    a0 = np.column_stack([np.ones(k * k), x, y])
    pinv0 = np.linalg.pinv(a0)  # 3 × k²
    resid0 = np.eye(k * k) - a0 @ pinv0  # symmetric, idempotent
    hinge = []
    for code in EDGES:
        pa, pb = (np.array(_POINTS[d], float) * half for d in divmod(code, 10))
        t = pb - pa
        n = np.array([-t[1], t[0]]) / np.hypot(*t)
        hinge.append(np.abs((x - pa[0]) * n[0] + (y - pa[1]) * n[1]))
    h = resid0 @ np.column_stack(hinge)  # hinge regressors with the plane part removed
    hnorm = (h * h).sum(axis=0)
    # the plane's coefficients in the hinge model: (plane fit of z) − c3 · (plane fit of |d|)
    plane_of_hinge = pinv0 @ np.column_stack(hinge)  # 3 × 16
    return pinv0, resid0, h, hnorm, plane_of_hinge


@lru_cache(maxsize=8)
def _cell_coords(k: int, cell: float) -> tuple[NDArray, NDArray]:
    """Cell-centre x (east) and y (north) of a tile's k² cells, row-major, metres."""
    c = (np.arange(k) + 0.5) * cell - k * cell / 2
    xx, yy = np.meshgrid(c, -c)  # row 0 is north
    return np.ascontiguousarray(xx.ravel()), np.ascontiguousarray(yy.ravel())


def _edge_direction(code: int) -> NDArray:
    a, b = divmod(code, 10)
    v = np.array(_POINTS[b], float) - np.array(_POINTS[a], float)
    return v / np.hypot(*v)


def _direction_code(gx: NDArray, gy: NDArray) -> NDArray[np.uint8]:
    ang = np.arctan2(gy, gx)
    return (np.round(ang / (np.pi / 4)).astype(np.int64) % 8 + 1).astype(np.uint8)


@register(
    "categories",
    CategoryParams,
    "Terrain categories on a 2 m tile grid: inclination, edge, state, height",
)
def compute_categories(
    dtm: NDArray,
    cell: float,
    params: CategoryParams | None = None,
    step: float | None = None,
    trend: tuple[NDArray, NDArray] | None = None,
) -> Categories:
    """Fit one or two planes to every tile of ``dtm`` (north-up, NaN nodata, ``cell`` m).

    With ``step`` (metres, below the tile size) tiles start every step instead
    of every tile: overlapping tiles, so a feature narrower than a tile (a road
    shoulder) lies whole inside some tile wherever the grid falls. Tile i then
    covers cells [i·step, i·step + k) and stands for the step-sized cell at its
    centre (``Categories.transform``).

    ``trend`` (east and north gradients per output tile, ``regional_gradient``)
    is subtracted from every tile before it is categorised: the tile as it lies
    on its regional slope.
    """
    return category_grids(dtm, cell, params, step, [trend])[0]


def category_grids(
    dtm: NDArray,
    cell: float,
    params: CategoryParams | None = None,
    step: float | None = None,
    trends: list[tuple[NDArray, NDArray] | None] | None = None,
) -> list[Categories]:
    """``compute_categories`` for each of ``trends`` (None: the tiles as they lie) on one
    tile grid. The residuals from one plane and the two-plane fits do not change when a
    plane is taken off a tile, so they are computed once for all the grids, in one
    compiled pass over the tiles."""
    params = params or CategoryParams()
    k = max(2, int(round(params.tile_size / cell)))
    if abs(k * cell - params.tile_size) > 0.5 * cell:
        raise ParameterError(f"tile_size {params.tile_size} cannot be snapped to {cell} m cells")
    dtm = np.asarray(dtm, dtype=np.float64)
    s = k if step is None else max(1, min(k, int(round(step / cell))))
    rows, cols = -(-dtm.shape[0] // s), -(-dtm.shape[1] // s)
    full = ((rows - 1) * s + k, (cols - 1) * s + k)
    if dtm.shape == full:  # the tiles cover it exactly: no padded copy (a large window's)
        padded = np.ascontiguousarray(dtm)
    else:
        padded = np.full(full, np.nan)
        padded[: dtm.shape[0], : dtm.shape[1]] = dtm
    _, _, h, hnorm, plane_of_hinge = _models(k, cell)
    sigma = params.noise
    if sigma is None:
        sigma = _noise([plane_residuals(dtm, cell, params)], k)
    gate = max(params.edge_min_rms, params.edge_noise * sigma)
    sigma_g = params.slope_noise
    if sigma_g is None:
        sigma_g = 0.0 if params.noise == 0 else _slope_noise([tile_slopes(dtm, cell, params)])
    clear_height = params.flat_height + params.clear_slope_noise * sigma_g * (k - 1) * cell
    flat_sigmas = params.flat_height / (sigma_g * (k - 1) * cell) if sigma_g > 0 else math.inf
    grids = list(trends or [None])
    n = rows * cols
    slopes = np.zeros((len(grids), 2, n))
    for j, trend in enumerate(grids):
        if trend is not None:
            slopes[j, 0] = np.asarray(trend[0], dtype=np.float64).ravel()
            slopes[j, 1] = np.asarray(trend[1], dtype=np.float64).ravel()
    xs, ys = _cell_coords(k, cell)
    # one compiled pass: plane and best hinge of every tile, its heights on every grid
    nodata, two, best, c3, gxs, gys, heights, reliefs, lying = fit_tiles(
        padded,
        k,
        s,
        rows,
        cols,
        xs,
        ys,
        h,
        hnorm,
        gate,
        params.edge_ratio,
        params.flat_noise * sigma,
        slopes,
    )

    def dm(v: NDArray) -> NDArray[np.uint8]:
        return np.clip(np.round(v * 10), 0, 254).astype(np.uint8)

    lying10 = dm(lying)
    lying10[nodata] = NODATA
    out = []
    for j in range(len(grids)):
        gx, gy, height, relief = gxs[j], gys[j], heights[j], reliefs[j]
        flat = relief < params.flat_height
        clear = (~flat & (relief >= clear_height)).astype(np.uint8)
        rise = np.hypot(gx, gy) * k * cell
        inclination = _direction_code(gx, gy)
        rise_dir = inclination.copy()
        rise_dir[np.hypot(gx, gy) <= params.clear_slope_noise * sigma_g] = 0
        grade = _grade(np.hypot(gx, gy), sigma_g)
        # A one-plane tile that is not flat always has a direction; an edged tile only
        # when its mean plane rises enough (a symmetric V or Λ has none).
        inclination[two & (rise < params.incline_height)] = 0

        edges = np.array(EDGES, dtype=np.uint8)
        orientation = np.where(two, edges[best], 0).astype(np.uint8)
        state = np.where(two, np.where(c3 < 0, 1, 2), 0).astype(np.uint8)

        # Extreme points: an E–W / N–S hinge whose slope along the edge dominates the
        # slope across it ends at a side midpoint: the highest one for a convex edge,
        # the lowest for a concave one.
        for code, (lo, hi) in ((15, (5, 1)), (37, (7, 3))):
            sel = two & (orientation == code)
            if not sel.any():
                continue
            # plane part of the hinge model, then its slope along the edge (from a=1|3 toward b=5|7)
            e = EDGES.index(code)
            gxh = gx[sel] - c3[sel] * plane_of_hinge[1, e]
            gyh = gy[sel] - c3[sel] * plane_of_hinge[2, e]
            d = _edge_direction(code)
            along = gxh * d[0] + gyh * d[1]  # rise per metre toward b
            ext = np.abs(along) > params.extreme_ratio * np.abs(c3[sel])
            rises_to_b = along > 0
            high_end = np.where(rises_to_b, lo, hi)  # b is 5 or 7 (lo), a is 1 or 3 (hi)
            low_end = np.where(rises_to_b, hi, lo)
            end = np.where(state[sel] == 1, high_end, low_end)
            ori = orientation[sel]
            ori[ext] = (11 * end[ext]).astype(np.uint8)
            orientation[sel] = ori

        inclination[flat] = 0
        orientation[flat] = 0
        state[flat] = 0
        height10, relief10 = dm(height), dm(relief)
        for band in (inclination, orientation, state, height10, relief10, clear, rise_dir, grade):
            band[nodata] = NODATA
        shape = (rows, cols)
        out.append(
            Categories(
                inclination.reshape(shape),
                orientation.reshape(shape),
                state.reshape(shape),
                height10.reshape(shape),
                k,
                k * cell,
                float(sigma),
                relief10.reshape(shape),
                None if s == k else s,
                lying10.reshape(shape),
                clear.reshape(shape),
                rise_dir.reshape(shape),
                grade.reshape(shape),
                flat_sigmas,
            )
        )
    return out


def _grade(gradient: NDArray, sigma_g: float) -> NDArray[np.uint8]:
    """Gradients in whole multiples of the slope noise ``sigma_g``, 0–254 (any gradient
    is 254 when ``sigma_g`` is 0)."""
    if sigma_g <= 0:
        return np.where(gradient > 0, 254, 0).astype(np.uint8)
    return np.clip(np.floor(gradient / sigma_g), 0, 254).astype(np.uint8)


def stack_rows(parts: list[Categories], keep: list[int]) -> Categories:
    """Categories of consecutive row bands stacked, keeping the first ``keep[i]`` tile rows of band i
    (bands of overlapping tiles are read with a margin whose tile rows belong to the next band)."""
    first = parts[0]

    def cat(name: str) -> NDArray[np.uint8]:
        arrays = [getattr(p, name) for p in parts]
        return np.concatenate([a[:n] for a, n in zip(arrays, keep, strict=True)])

    return Categories(
        cat("inclination"),
        cat("orientation"),
        cat("state"),
        cat("height10"),
        first.cells_per_tile,
        first.tile_size,
        float(np.median([p.noise for p in parts])),
        None if first.relief10 is None else cat("relief10"),
        first.step_cells,
        None if first.lying10 is None else cat("lying10"),
        None if first.clear is None else cat("clear"),
        None if first.rise is None else cat("rise"),
        None if first.grade is None else cat("grade"),
        min(p.flat_sigmas for p in parts),
    )


def plane_residuals(dtm: NDArray, cell: float, params: CategoryParams) -> NDArray[np.float64]:
    """One-plane residual RMS of every whole tile with data (abutting tiles)."""
    k = max(2, int(round(params.tile_size / cell)))
    dtm = np.asarray(dtm, dtype=np.float64)
    rows, cols = dtm.shape[0] // k, dtm.shape[1] // k
    z: NDArray[np.float64] = (
        dtm[: rows * k, : cols * k]
        .reshape(rows, k, cols, k)
        .transpose(0, 2, 1, 3)
        .reshape(rows * cols, k * k)
    )
    z = z[~np.isnan(z).any(axis=1)]
    _, resid0, *_ = _models(k, cell)
    r0 = z @ resid0
    return np.sqrt((r0 * r0).sum(axis=1) / (k * k))


def tile_slopes(dtm: NDArray, cell: float, params: CategoryParams) -> NDArray[np.float64]:
    """Second differences of the fitted slopes of abutting tiles, along rows and columns,
    east and north slopes together (NaN where a tile has nodata)."""
    k = max(2, int(round(params.tile_size / cell)))
    dtm = np.asarray(dtm, dtype=np.float64)
    rows, cols = dtm.shape[0] // k, dtm.shape[1] // k
    t = dtm[: rows * k, : cols * k].reshape(rows, k, cols, k).transpose(0, 2, 1, 3)
    u = (np.arange(k) - (k - 1) / 2) * cell
    g = (t * u[None, None, None, :]).sum(axis=(2, 3)) / (k * (u * u).sum())  # east
    n = (t * -u[None, None, :, None]).sum(axis=(2, 3)) / (k * (u * u).sum())  # north
    out = []
    for a in (g, n):
        out += [
            (a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]).ravel(),
            (a[2:] - 2 * a[1:-1] + a[:-2]).ravel(),
        ]
    return np.concatenate(out)


def _slope_noise(diffs: list[NDArray]) -> float:
    """Noise σ of a tile's slope from second differences of abutting tiles' slopes: their
    median absolute value as a normal σ (a second difference of three independent
    slopes has √6 σ); 0 with too few tiles."""
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    d = d[np.isfinite(d)]
    if d.size < MIN_NOISE_TILES:
        return 0.0
    return float(1.4826 * np.median(np.abs(d)) / np.sqrt(6.0))


def measure_slope_noise(dtm: NDArray, cell: float, params: CategoryParams) -> float:
    """The noise σ of a tile's slope as ``compute_categories`` measures it (``slope_noise=None``)."""
    return _slope_noise([tile_slopes(dtm, cell, params)])


def measure_noise(dtm: NDArray, cell: float, params: CategoryParams) -> float:
    """The DTM's noise σ as ``compute_categories`` measures it (``noise=None``)."""
    k = max(2, int(round(params.tile_size / cell)))
    return _noise([plane_residuals(dtm, cell, params)], k)


def _noise(residuals: list[NDArray], k: int) -> float:
    """Noise σ from one-plane residual RMS of tiles: their median, corrected for the 3 fitted
    parameters; 0 with fewer than MIN_NOISE_TILES tiles."""
    r = np.concatenate(residuals) if residuals else np.zeros(0)
    if r.size < MIN_NOISE_TILES:
        return 0.0
    return float(np.median(r)) * float(np.sqrt(k * k / (k * k - 3)))


def regional_gradient(
    dtm: NDArray,
    cell: float,
    params: CategoryParams,
    window: float,
    step: float | None = None,
) -> tuple[NDArray, NDArray]:
    """The regional slope (east, north gradients) under every tile of
    ``compute_categories(dtm, cell, params, step)``: the median, over a ``window``
    (metres) square, of the one-plane gradients of the abutting tiles.

    A narrow object on a slope (a ditch across a 12 % slope: at 2 m tiles the
    slope adds 0.24 m across each tile and dominates the ditch's banks, Sjövall
    §5.1.1) is categorised on this slope as on level ground. The median, not the
    window's least-squares plane: at the foot of a ridge or a hillside the mean
    slope lies between the two sides and leaves a ditch-like dip in the bend; the
    median follows the side that fills most of the window, so a bend stays a bend.
    """
    k = max(2, int(round(params.tile_size / cell)))
    z = np.asarray(dtm, dtype=np.float64)
    rows, cols = z.shape[0] // k, z.shape[1] // k
    if rows == 0 or cols == 0:
        gx = gy = np.zeros((rows, cols))
    else:
        t: NDArray[np.float64] = (
            z[: rows * k, : cols * k]
            .reshape(rows, k, cols, k)
            .transpose(0, 2, 1, 3)
            .reshape(rows * cols, k * k)
        )
        pinv0, *_ = _models(k, cell)
        coef = np.nan_to_num(t @ pinv0.T)  # tiles with nodata: 0 gradient
        size = max(1, int(round(window / (k * cell))))
        # a wide window takes its median over every stride-th tile (at most ~16 a
        # side), so the cost does not grow with the window's area
        stride = max(1, size // 16)
        gx, gy = (_strided_median(coef[:, i].reshape(rows, cols), size, stride) for i in (1, 2))
    s = k if step is None else max(1, min(k, int(round(step / cell))))
    out_r, out_c = -(-z.shape[0] // s), -(-z.shape[1] // s)
    # the abutting tile holding each output tile's centre (clamped at the border)
    ri = np.clip((np.arange(out_r) * s + k // 2) // k, 0, max(rows - 1, 0))
    ci = np.clip((np.arange(out_c) * s + k // 2) // k, 0, max(cols - 1, 0))
    if rows == 0 or cols == 0:
        return np.zeros((out_r, out_c)), np.zeros((out_r, out_c))
    return gx[np.ix_(ri, ci)], gy[np.ix_(ri, ci)]


def _strided_median(a: NDArray, size: int, stride: int) -> NDArray:
    """Median over ``size`` × ``size`` windows of ``a`` (``scipy.ndimage.median_filter``
    with ``mode="nearest"``, compiled: ``_median_kernels``); with ``stride`` > 1 over the
    samples every ``stride`` tiles, taken on that coarse grid and spread back."""
    if stride == 1 or a.size == 0:
        return median_filter(a, size)
    # the first sample half a stride in; an axis shorter than that (a thin window)
    # is sampled at its middle tile, so the coarse grid is never empty
    r0, c0 = (stride // 2 if n > stride // 2 else (n - 1) // 2 for n in a.shape)
    coarse = median_filter(a[r0::stride, c0::stride], max(1, -(-size // stride)))
    r = np.minimum(np.arange(a.shape[0]) // stride, coarse.shape[0] - 1)
    c = np.minimum(np.arange(a.shape[1]) // stride, coarse.shape[1] - 1)
    return coarse[np.ix_(r, c)]


def measure_noise_by_bands(
    read_rows: Callable[[int, int], NDArray],
    height: int,
    cell: float,
    params: CategoryParams,
    band_rows: int,
) -> float:
    """The DTM's noise σ measured over bands as ``categories_by_bands`` measures it."""
    k = max(2, int(round(params.tile_size / cell)))
    band = max(k, band_rows // k * k)
    res = [
        plane_residuals(read_rows(r, min(height, r + band)), cell, params)
        for r in range(0, height, band)
    ]
    return _noise(res, k)


def measure_slope_noise_by_bands(
    read_rows: Callable[[int, int], NDArray],
    height: int,
    cell: float,
    params: CategoryParams,
    band_rows: int,
) -> float:
    """The noise σ of a tile's slope measured over bands as ``categories_by_bands`` measures it."""
    k = max(2, int(round(params.tile_size / cell)))
    band = max(k, band_rows // k * k)
    diffs = [
        tile_slopes(read_rows(r, min(height, r + band)), cell, params)
        for r in range(0, height, band)
    ]
    return _slope_noise(diffs)


def categories_by_bands(
    read_rows: Callable[[int, int], NDArray],
    height: int,
    cell: float,
    params: CategoryParams,
    band_rows: int,
    step: float | None = None,
    windows: Sequence[float | None] = (None,),
) -> list[Categories]:
    """Categories of a DTM read in bands of about ``band_rows`` rows (``read_rows(r0, r1)``),
    so memory follows the band, one grid per entry of ``windows``: None for the tiles
    as they lie, a window in metres for tiles set on their regional slope
    (``regional_gradient``, read with half a window of rows around each band).
    Overlapping tiles (``step``) read a tile's overlap beyond each band; the tiles
    starting there belong to the next band."""
    k = max(2, int(round(params.tile_size / cell)))
    s = k if step is None else max(1, min(k, int(round(step / cell))))
    whole = int(np.lcm(k, s))
    band = max(whole, band_rows // whole * whole)  # whole tiles and whole steps
    if params.noise is None:  # measured once over all bands, as over the whole DTM (the raw DTM's)
        res = [
            plane_residuals(read_rows(r, min(height, r + band)), cell, params)
            for r in range(0, height, band)
        ]
        params = params.model_copy(update={"noise": _noise(res, k)})
    if params.slope_noise is None:  # likewise once over all bands
        params = params.model_copy(
            update={
                "slope_noise": 0.0
                if params.noise == 0
                else measure_slope_noise_by_bands(read_rows, height, cell, params, band_rows)
            }
        )
    # the regional slope of a band reads half a window (whole steps and tiles) around it
    widest = max((w for w in windows if w is not None), default=None)
    margin = 0 if widest is None else -(-int(round(widest / cell / 2)) // whole) * whole
    parts: list[list[Categories]] = [[] for _ in windows]
    keep = []
    for r in range(0, height, band):
        stop = min(height, r + band + (k - s))
        trends: list[tuple[NDArray, NDArray] | None] = []
        if widest is not None:
            a, b = max(0, r - margin), min(height, stop + margin)
            around = read_rows(a, b)
            first, n = (r - a) // s, -(-(stop - r) // s)
        for w in windows:
            if w is None:
                trends.append(None)
                continue
            gx, gy = regional_gradient(around, cell, params, w, step)
            trends.append((gx[first : first + n], gy[first : first + n]))
        for i, cats in enumerate(category_grids(read_rows(r, stop), cell, params, step, trends)):
            parts[i].append(cats)
        keep.append(-(-min(band, height - r) // s))
    return [stack_rows(p, keep) for p in parts]
