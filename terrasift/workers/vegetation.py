"""Tree and bush bins, vegetation coverage and no-go screening (NIST §4).

The first select/reject pass over the bin grid gives, for every bin, the count
n, the lowest point (x_min, y_min, z_min), z_mean and z_max. For a bin rejected
as a ground candidate:

    z_ground = min(surface(x_min, y_min), z_min)
    tree  when n > min_points, z_max − z_ground > tree_height and z_mean − z_ground ≥ tree_mean
    bush  otherwise when n > min_points and z_mean − z_ground ≥ bush_mean

Every other non-empty bin is open. Coverage is tree (bush) bins over non-empty
bins. The surface is a TIN over the ground points the caller passes.

Two additions make the rule usable on airborne clouds, whose 1 m bins hold a
handful of points rather than the hundreds of a ground-based scan:

- ``support``: the n > min_points test counts the points of the k × k bins
  centred on a bin (k odd, 1 = the seed's rule), so the coverage raster keeps
  its 1 m cells; the height tests still use the bin's own points.
- ``screen_tol``: a bin whose lowest point lies more than ``screen_tol`` above
  the ground surface is rejected too. NIST deletes such a point from the ground
  TIN by screening (§3.2) and relies on TIN masking to block the bin; without a
  mask, a bin wholly inside a dense crown would otherwise pass the RMS test and
  count as open.

Bins are flat arrays in ``Grid`` order (row-major from the lower-left corner);
``north_up`` turns one into a raster with row 0 to the north.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator
from scipy import ndimage

from terrasift.workers.bins import BinStats, Grid, bin_statistics, plane_fit_statistics
from terrasift.workers.registry import StageParams, register
from terrasift.workers.surface import TinSurface

EMPTY, OPEN, BUSH, TREE, BUILDING = 0, 1, 2, 3, 4
BIN_NAMES = {EMPTY: "empty", OPEN: "open", BUSH: "bush", TREE: "tree", BUILDING: "building"}
LOW_VEG, MED_VEG, HIGH_VEG, UNCLASSIFIED = 3, 4, 5, 1


class VegetationParams(StageParams):
    """Parameters of tree/bush bin classification (NIST §4)."""

    cell: float = Field(1.0, gt=0, le=100)
    """Bin size in metres; the spine builds the grid with it and writes
    ``coverage.tif`` at this cell. 1 m is the seed's grid (§6.2) and the
    scale at which a vehicle meets a bush or a trunk."""
    min_points: int = Field(20, ge=0, le=100_000)
    """A bin is judged only when its support holds more than this many points (seed: n > 20)."""
    support: int | None = Field(None, ge=1, le=15)
    """Odd width, in bins, of the window whose points count towards ``min_points``;
    1 is the seed's rule, None picks the smallest width at which the median
    non-empty window holds at least 2 × (min_points + 1) points."""
    tree_height: float = Field(3.75, gt=0, le=100)
    """Tree: z_max − z_ground must exceed this (m)."""
    tree_mean: float = Field(0.75, ge=0, le=100)
    """Tree: z_mean − z_ground must reach this (m)."""
    bush_mean: float = Field(0.25, ge=0, le=100)
    """Bush: z_mean − z_ground must reach this (m)."""
    rms_tol: float = Field(0.1, gt=0, le=10)
    """Select/reject: a bin whose elevation RMS exceeds this (m) is rejected as a ground candidate."""
    bin_fit: Literal["flat", "plane"] = "flat"
    """RMS about the bin mean (seed §3.1) or about a least-squares plane (seed §7),
    so smooth steep bins are not rejected."""
    screen_tol: float | None = Field(0.25, gt=0, le=100)
    """Reject a bin whose lowest point is this far (m) above the ground surface;
    None keeps the seed's RMS-only rejection."""
    mow_height: float | None = Field(None, gt=0, le=100)
    """Mow points higher than this (m) above ground before a second select/reject
    pass whose tree/bush bins are the no-go bins (seed §4, e.g. 3 m)."""

    @field_validator("support")
    @classmethod
    def _odd(cls, v: int | None) -> int | None:
        if v is not None and v % 2 == 0:
            raise ValueError("support must be odd (a window centred on the bin)")
        return v


@dataclass(frozen=True)
class VegetationBins:
    """Per-bin result, flat arrays of ``grid.size`` in grid order.

    ``bin_class``: 0 empty, 1 open, 2 bush, 3 tree, 4 building (a bin
    holding building points and no vegetation, see ``mark_buildings``). ``nogo``: bins a vehicle
    should avoid (vegetation below ``mow_height`` when mowing, else every tree
    or bush bin). ``height``: z_max − z_ground (NaN when empty). ``support``:
    the window width that was used.
    """

    grid: Grid
    bin_class: NDArray[np.uint8]
    nogo: NDArray[np.bool_]
    n: NDArray[np.int64]
    height: NDArray[np.float64]
    support: int

    @property
    def counts(self) -> dict[str, int]:
        """Bins per class: ``empty``, ``open``, ``bush``, ``tree``."""
        return class_counts(self.bin_class)

    @property
    def tree_coverage(self) -> float:
        return coverage_from_counts(self.counts)[0]

    @property
    def bush_coverage(self) -> float:
        return coverage_from_counts(self.counts)[1]

    def raster(self) -> NDArray[np.uint8]:
        """``bin_class`` as a north-up raster (the coverage.tif band)."""
        return north_up(self.bin_class, self.grid)

    def crop(self, sub: Grid) -> VegetationBins:
        """The part of this result on ``sub``, a window of the same grid (e.g. a block's core)."""
        g = self.grid
        ix0, iy0 = round((sub.x0 - g.x0) / g.cell), round((sub.y0 - g.y0) / g.cell)
        tol = 1e-6 * g.cell
        if (
            abs(sub.cell - g.cell) > tol
            or abs(sub.x0 - (g.x0 + ix0 * g.cell)) > tol
            or abs(sub.y0 - (g.y0 + iy0 * g.cell)) > tol
            or ix0 < 0
            or iy0 < 0
            or ix0 + sub.nx > g.nx
            or iy0 + sub.ny > g.ny
        ):
            raise ValueError("crop grid is not an aligned window of the bin grid")

        def cut(a: NDArray) -> NDArray:
            return a.reshape(self.grid.ny, self.grid.nx)[
                iy0 : iy0 + sub.ny, ix0 : ix0 + sub.nx
            ].ravel()

        return VegetationBins(
            sub, cut(self.bin_class), cut(self.nogo), cut(self.n), cut(self.height), self.support
        )


def class_counts(bin_class: NDArray) -> dict[str, int]:
    """Number of empty, open, bush, tree and building bins; sum these over blocks to combine."""
    c = np.bincount(np.ravel(bin_class).astype(np.int64), minlength=5)
    return {name: int(c[code]) for code, name in BIN_NAMES.items()}


def mark_buildings(bins: VegetationBins, building_xyz: NDArray[np.float64]) -> VegetationBins:
    """``bins`` with every empty or open bin that holds a building point set to BUILDING.

    Vegetation bins are judged without the building points, so a roof is not a
    tree; a bin where a crown overhangs a roof stays vegetation.
    """
    g = bins.grid
    flat = g.index(building_xyz[:, 0], building_xyz[:, 1]) if building_xyz.shape[0] else None
    if flat is None or not (flat >= 0).any():
        return bins
    has = np.zeros(g.size, bool)
    has[flat[flat >= 0]] = True
    cls = bins.bin_class.copy()
    cls[has & (cls <= OPEN)] = BUILDING
    return VegetationBins(g, cls, bins.nogo, bins.n, bins.height, bins.support)


def coverage_from_counts(counts: dict[str, int]) -> tuple[float, float]:
    """(tree_coverage, bush_coverage) over non-empty bins (buildings included); 0
    when every bin is empty."""
    nonempty = counts["open"] + counts["bush"] + counts["tree"] + counts.get("building", 0)
    if nonempty == 0:
        return 0.0, 0.0
    return counts["tree"] / nonempty, counts["bush"] / nonempty


def north_up(flat: NDArray, grid: Grid) -> NDArray:
    """A flat per-bin array (row 0 = south) as a north-up raster (row 0 = north)."""
    return np.asarray(flat).reshape(grid.ny, grid.nx)[::-1]


def auto_support(n: NDArray, grid: Grid, min_points: int) -> int:
    """Smallest odd window width whose median non-empty window holds ≥ 2 (min_points + 1) points.

    The margin of two keeps most bins judged where counts scatter about the median.
    """
    need = 2 * (min_points + 1)
    n2 = np.asarray(n).reshape(grid.ny, grid.nx)
    if not (n2 > 0).any():
        return 1
    for k in range(1, 16, 2):
        win = _window_sum(n2, k)
        if np.median(win[n2 > 0]) >= need:
            return k
    return 15


def with_support(params: VegetationParams, density: float) -> VegetationParams:
    """``params`` with ``support`` fixed: the given width, else the one for
    ``density`` (the job's mean points per m², one value for the whole job so
    neighbouring blocks judge bins alike)."""
    if params.support is not None:
        return params
    support = support_for_density(density, params.cell, params.min_points)
    return params.model_copy(update={"support": support})


def support_for_density(density: float, cell: float, min_points: int = 20) -> int:
    """Smallest odd window width whose k × k bins expect ≥ 2 (min_points + 1) points
    at ``density`` points per m². The spine can fix ``support`` once per job from
    the header's point count and area, so neighbouring blocks never differ."""
    need = 2 * (min_points + 1)
    for k in range(1, 16, 2):
        if density * (k * cell) ** 2 >= need:
            return k
    return 15


def _window_sum(n2: NDArray, k: int) -> NDArray[np.int64]:
    if k == 1:
        return n2.astype(np.int64)
    return ndimage.correlate(
        n2.astype(np.int64), np.ones((k, k), np.int64), mode="constant", cval=0
    )


@dataclass(frozen=True)
class _Pass:
    tree: NDArray[np.bool_]
    bush: NDArray[np.bool_]
    height: NDArray[np.float64]


def _judge(
    xyz: NDArray,
    grid: Grid,
    params: VegetationParams,
    surface: Callable[[NDArray, NDArray], NDArray] | None,
    mask: NDArray[np.bool_] | None,
    support: int | None,
) -> tuple[_Pass, BinStats, int]:
    """One select/reject pass and the tree/bush criteria on its rejected bins."""
    st = bin_statistics(xyz, grid)
    nonempty = st.n > 0
    if params.bin_fit == "plane":
        rms = plane_fit_statistics(xyz, grid).rms
        rms = np.where(np.isnan(rms), st.rms, rms)  # too few points for a plane: about the mean
    else:
        rms = st.rms
    k = support if support is not None else auto_support(st.n, grid, params.min_points)
    n_support = _window_sum(st.n.reshape(grid.ny, grid.nx), k).ravel()

    zsurf = np.full(grid.size, np.inf)
    low = np.flatnonzero(nonempty)
    if surface is not None and low.size:
        zsurf[low] = surface(xyz[st.lowest[low], 0], xyz[st.lowest[low], 1])
    with np.errstate(invalid="ignore"):
        zground = np.where(nonempty, np.minimum(zsurf, st.zmin), np.nan)
        rejected = nonempty & (rms > params.rms_tol)
        if params.screen_tol is not None:
            rejected |= nonempty & (st.zmin - zsurf > params.screen_tol)
        if mask is not None:
            rejected |= nonempty & np.asarray(mask, dtype=bool)
        enough = n_support > params.min_points
        above_max = st.zmax - zground
        above_mean = st.zmean - zground
        tree = (
            rejected & enough & (above_max > params.tree_height) & (above_mean >= params.tree_mean)
        )
        bush = rejected & enough & ~tree & (above_mean >= params.bush_mean)
    return _Pass(tree, bush, above_max), st, k


@register(
    "vegetation",
    VegetationParams,
    "Tree/bush bins and vegetation coverage from select/reject statistics (NIST §4)",
)
def classify_bins(
    xyz: NDArray[np.float64],
    is_ground: NDArray[np.bool_],
    grid: Grid,
    params: VegetationParams | None = None,
    *,
    mask: NDArray[np.bool_] | None = None,
    surface: Callable[[NDArray, NDArray], NDArray] | None = None,
) -> VegetationBins:
    """Classify every bin of ``grid`` as empty, open, bush or tree.

    ``xyz`` are all points of the block (with its buffer: the support window
    reaches into neighbours), ``is_ground`` marks the points the ground surface
    is built from. ``mask`` (flat, per bin) blocks bins as TIN masking does;
    ``surface`` replaces the TIN over the ground points (any z(x, y) callable).
    Without ground points z_ground is the bin's z_min.
    """
    params = params or VegetationParams()
    xyz = np.asarray(xyz, dtype=np.float64)
    is_ground = np.asarray(is_ground, dtype=bool)
    if surface is None and is_ground.any():
        surface = ground_surface(xyz[is_ground], grid)

    first, st, k = _judge(xyz, grid, params, surface, mask, params.support)
    bin_class = np.where(st.n > 0, OPEN, EMPTY).astype(np.uint8)
    bin_class[first.bush] = BUSH
    bin_class[first.tree] = TREE

    if params.mow_height is None:
        nogo = first.tree | first.bush
    else:
        if surface is None:
            hag = xyz[:, 2] - _bin_floor(xyz, grid, st)
        else:
            hag = xyz[:, 2] - surface(xyz[:, 0], xyz[:, 1])
        mowed = xyz[hag <= params.mow_height]
        second, _, _ = _judge(mowed, grid, params, surface, mask, k)
        nogo = second.tree | second.bush
    return VegetationBins(grid, bin_class, nogo, st.n, first.height, k)


def ground_surface(ground_xyz: NDArray[np.float64], grid: Grid) -> TinSurface | None:
    """TIN over the centroid of the ground points in each bin.

    A centroid of points on a plane lies on that plane, so planar patches are
    kept exactly while noise averages out; and the TIN has one vertex per bin
    instead of one per point (a TIN of a few hundred thousand vertices costs
    seconds to locate points in). None when no ground point falls on the grid.
    """
    flat = grid.index(ground_xyz[:, 0], ground_xyz[:, 1])
    keep = flat >= 0
    if not keep.any():
        return None
    f = flat[keep]
    n = np.bincount(f, minlength=grid.size)
    local = ground_xyz[keep] - (grid.x0, grid.y0, 0.0)
    sums = [np.bincount(f, weights=local[:, i], minlength=grid.size) for i in range(3)]
    occ = n > 0
    cen = np.column_stack([s[occ] / n[occ] for s in sums]) + (grid.x0, grid.y0, 0.0)
    return TinSurface(cen)


def _bin_floor(xyz: NDArray, grid: Grid, st: BinStats) -> NDArray:
    """z_min of each point's bin (ground stand-in when no ground points exist)."""
    flat = grid.index(xyz[:, 0], xyz[:, 1])
    return np.where(flat >= 0, st.zmin[np.maximum(flat, 0)], xyz[:, 2])


def height_classes(height_above_ground: NDArray) -> NDArray[np.uint8]:
    """ASPRS vegetation class by height above ground: 3 low (< 0.5 m), 4 medium
    (0.5–2 m), 5 high (> 2 m); 1 (unclassified) where the height is NaN.

    Meant for the non-ground points; points below ground fall in class 3.
    """
    h = np.asarray(height_above_ground, dtype=np.float64)
    out = np.full(h.shape, UNCLASSIFIED, dtype=np.uint8)
    ok = np.isfinite(h)
    out[ok] = np.where(h[ok] < 0.5, LOW_VEG, np.where(h[ok] <= 2.0, MED_VEG, HIGH_VEG))
    return out
