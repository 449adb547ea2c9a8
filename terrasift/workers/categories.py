"""Terrain categories on a tile grid over the DTM (Sjövall §1.4, DESIGN §5.7).

Each tile (default 2 m = 4 × 4 cells of a 0.5 m DTM) is fitted by one plane, or
by two planes meeting along an edge between two of its eight boundary points
when that fits clearly better. All tiles are fitted at once: the k² cells of
every tile form one stacked array, the one-plane fit is a fixed projection and
each of the 16 two-plane ("hinge") models adds one regressor |distance to the
edge line|, so its gain over the plane follows from one more projection
(Frisch–Waugh). The result per tile:

- inclination 0–8: 0 none, else the direction (1 E, 2 NE, 3 N … 8 SE,
  counter-clockwise from east) the mean plane rises toward;
- orientation: the edge ``ab`` (a < b), an extreme point ``aa`` or 0;
- state: 0 one plane, 1 convex edge (ridge-like), 2 concave edge (ditch-like);
- height10: (max − min) inside the tile in decimetres.

Tiles with any nodata cell, and partial tiles at the right/bottom border, carry
``NODATA`` (255) in all four bands.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from rasterio import Affine

from terrasift.errors import ParameterError
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


@dataclass(frozen=True)
class Categories:
    """The four category bands on the tile grid, with the tile geometry."""

    inclination: NDArray[np.uint8]
    orientation: NDArray[np.uint8]
    state: NDArray[np.uint8]
    height10: NDArray[np.uint8]
    cells_per_tile: int
    tile_size: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.inclination.shape

    @property
    def nodata(self) -> NDArray[np.bool_]:
        return self.inclination == NODATA

    def transform(self, dtm_transform: Affine) -> Affine:
        """The tile grid's geotransform given the DTM's."""
        return dtm_transform @ Affine.scale(self.cells_per_tile)

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
    dtm: NDArray, cell: float, params: CategoryParams | None = None
) -> Categories:
    """Fit one or two planes to every tile of ``dtm`` (north-up, NaN nodata, ``cell`` m)."""
    params = params or CategoryParams()
    k = max(2, int(round(params.tile_size / cell)))
    if abs(k * cell - params.tile_size) > 0.5 * cell:
        raise ParameterError(f"tile_size {params.tile_size} cannot be snapped to {cell} m cells")
    dtm = np.asarray(dtm, dtype=np.float64)
    rows, cols = -(-dtm.shape[0] // k), -(-dtm.shape[1] // k)
    padded = np.full((rows * k, cols * k), np.nan)
    padded[: dtm.shape[0], : dtm.shape[1]] = dtm
    z = padded.reshape(rows, k, cols, k).transpose(0, 2, 1, 3).reshape(rows * cols, k * k)

    nodata: NDArray[np.bool_] = np.isnan(z).any(axis=1)  # type: ignore[assignment]
    z = np.where(nodata[:, None], 0.0, z)
    z = z - z.mean(axis=1, keepdims=True)
    height = z.max(axis=1) - z.min(axis=1)

    pinv0, resid0, h, hnorm, plane_of_hinge = _models(k, cell)
    coef0 = z @ pinv0.T  # (n, 3): c, gx, gy
    r0 = z @ resid0
    rss0 = (r0 * r0).sum(axis=1)
    proj = r0 @ h  # (n, 16)
    gain = proj * proj / hnorm
    best = gain.argmax(axis=1)
    n = z.shape[0]
    idx = np.arange(n)
    best_gain = gain[idx, best]
    c3 = proj[idx, best] / hnorm[best]
    rms0 = np.sqrt(rss0 / (k * k))
    two = (rms0 > params.edge_min_rms) & (rss0 - best_gain <= params.edge_ratio * rss0)

    flat = height < params.flat_height
    gx, gy = coef0[:, 1], coef0[:, 2]
    rise = np.hypot(gx, gy) * k * cell
    inclination = _direction_code(gx, gy)
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
    height10 = np.clip(np.round(height * 10), 0, 254).astype(np.uint8)
    for band in (inclination, orientation, state, height10):
        band[nodata] = NODATA
    shape = (rows, cols)
    return Categories(
        inclination.reshape(shape),
        orientation.reshape(shape),
        state.reshape(shape),
        height10.reshape(shape),
        k,
        k * cell,
    )
