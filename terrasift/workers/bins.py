"""Per-bin statistics on a regular grid: the select/reject basis of NIST §2.

Sums over the points of each bin are accumulated by small compiled loops
(numba) in point order, as ``np.bincount`` would, so one call costs one or two
passes over the points whatever the number of bins; the per-bin arithmetic
stays in numpy. Bins are addressed row-major from the grid origin (lower-left
corner): ``flat = iy * nx + ix``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from terrasift.errors import ParameterError, ProcessingError
from terrasift.workers._kernels import (
    _ON_EDGE,
    _bounds_kernel,
    _cell_counting_sort,
    _index_kernel,
    _level_sums,
    _min_argmin,
    _plane_residuals,
    _plane_sums,
    _squared_deviations,
)

#: Local origins of blocks are multiples of this many metres, a common multiple
#: of every usual bin size (0.5 … 240 m), so bins of two blocks line up and a
#: point near a block edge falls in the same bin whichever block it is in.
ANCHOR = 240.0


#: Bin sizes (1 m and up, to 0.1 m) that divide ``ANCHOR``: a grid of one of them,
#: anchored on a multiple of itself in coordinates whose origin is a multiple of
#: ``ANCHOR``, lines up with every block's whatever its extent.
ANCHORED_CELLS = np.array([c / 10 for c in range(10, 2401) if 2400 % c == 0])


def snap_cell(cell: float) -> float:
    """The bin size of ``ANCHORED_CELLS`` nearest ``cell`` by ratio (``cell`` itself
    below 1 m or above ``ANCHOR``): cells derived from two blocks' slightly different
    densities snap to the same size, so their bins coincide where the blocks overlap."""
    if not (ANCHORED_CELLS[0] <= cell <= ANCHOR):
        return float(cell)
    return float(ANCHORED_CELLS[np.argmin(np.abs(np.log(ANCHORED_CELLS / cell)))])


def anchored_origin(xy: NDArray[np.float64], anchor: float = ANCHOR) -> NDArray[np.float64]:
    """The multiple of ``anchor`` at or below the smallest x and y of ``xy``."""
    xy = np.asarray(xy, dtype=np.float64)
    # Column by column: a reduction over axis 0 of (n, 2) rows is several times slower.
    return np.floor(np.array([xy[:, 0].min(), xy[:, 1].min()]) / anchor) * anchor


def cell_order(x: NDArray[np.float64], y: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Stable permutation putting points in row-major order of the ``cell``-sized
    squares of a grid through the origin.

    A compiled counting sort on the cell key (``_cell_counting_sort``) when the
    keys span at most a few times as many cells as there are points: the
    stable order is unique, so it is the permutation of a stable argsort, at
    a fraction of the cost. Otherwise the key is sorted by numpy's radix sort
    on 16-bit digits (one pass when there are fewer than 65536 cells, two up
    to 2**32).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.size:
        order = _cell_counting_sort(
            x.reshape(-1), y.reshape(-1), float(cell), 4 * x.size + (1 << 20)
        )
        if order.size == x.size:
            return order
    ix = np.floor(x / cell).astype(np.int64)
    iy = np.floor(y / cell).astype(np.int64)
    if ix.size:
        ix -= ix.min()
        iy -= iy.min()
    key = iy * (int(ix.max()) + 1) + ix if ix.size else ix
    if key.size == 0 or int(key.max()) >= 1 << 32:
        return np.argsort(key, kind="stable")
    order = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    if int(key.max()) >= 1 << 16:
        order = order[np.argsort((key[order] >> 16).astype(np.uint16), kind="stable")]
    return order


def bounds(x: NDArray, y: NDArray) -> tuple[np.floating, np.floating, np.floating, np.floating]:
    """``x.min(), x.max(), y.min(), y.max()`` in one compiled pass for float64
    input (four numpy reductions over strided columns cost several times more)."""
    if x.size and x.size == y.size and x.dtype == np.float64 and y.dtype == np.float64:
        x0, x1, y0, y1 = _bounds_kernel(x.reshape(-1), y.reshape(-1))
        return np.float64(x0), np.float64(x1), np.float64(y0), np.float64(y1)
    return x.min(), x.max(), y.min(), y.max()


MAX_CELLS_PER_AXIS = 1 << 31  # a grid this wide could never be held (2^62 cells)


@dataclass(frozen=True)
class Grid:
    """A regular grid: lower-left corner, square cell size, shape (ny, nx)."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int

    @classmethod
    def covering(cls, x: NDArray, y: NDArray, cell: float) -> Grid:
        """The smallest grid of ``cell``-sized bins, anchored on a multiple of
        ``cell``, that holds every point."""
        xmin, xmax, ymin, ymax = bounds(x, y)
        x0 = np.floor(xmin / cell) * cell
        y0 = np.floor(ymin / cell) * cell
        if not np.all(np.isfinite([xmin, xmax, ymin, ymax])):
            raise ProcessingError("point coordinates are not finite numbers")
        span = np.array([(xmax - x0) / cell, (ymax - y0) / cell])
        if not np.all(np.isfinite(span)) or span.max() >= MAX_CELLS_PER_AXIS:
            # a cell size a parameter made tiny (5e-324 is a valid positive float) would
            # overflow the integer shape or ask for more cells than any memory holds
            raise ParameterError(
                f"a grid of {cell:.3g} m cells over {xmax - xmin:.6g} x {ymax - ymin:.6g} m of "
                f"points needs more than {MAX_CELLS_PER_AXIS} cells a side; a cell size or "
                "spacing parameter of the job is too small"
            )
        # A point on the last edge opens a bin of its own, as ``index`` puts it there.
        nx = int(np.floor(span[0] + _ON_EDGE)) + 1
        ny = int(np.floor(span[1] + _ON_EDGE)) + 1
        return cls(float(x0), float(y0), float(cell), nx, ny)

    @property
    def size(self) -> int:
        return self.nx * self.ny

    def index(self, x: NDArray, y: NDArray) -> NDArray[np.int64]:
        """Flat bin index of each point, -1 for points outside the grid.

        One compiled pass (``_index_kernel``) instead of a dozen numpy passes
        over millions of points.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        out = np.empty(x.size, dtype=np.int64)
        _index_kernel(
            x.reshape(-1), y.reshape(-1), self.x0, self.y0, self.cell, self.nx, self.ny, out
        )
        return out.reshape(x.shape)

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Flat arrays of bin-centre x and y, in flat-index order."""
        xs = self.x0 + (np.arange(self.nx) + 0.5) * self.cell
        ys = self.y0 + (np.arange(self.ny) + 0.5) * self.cell
        gx, gy = np.meshgrid(xs, ys)
        return gx.ravel(), gy.ravel()


@dataclass(frozen=True)
class BinStats:
    """Statistics of the points in each bin, as flat arrays of ``grid.size``.

    Empty bins have n = 0 and NaN statistics; ``lowest`` is -1 there.
    ``rms`` is the root-mean-square deviation of z about the bin mean.
    """

    grid: BinGrid
    n: NDArray[np.int64]
    zmin: NDArray[np.float64]
    zmax: NDArray[np.float64]
    zmean: NDArray[np.float64]
    rms: NDArray[np.float64]
    lowest: NDArray[np.int64]  # index (into the input points) of each bin's lowest point


def lowest_per_bin(
    flat: NDArray[np.int64],
    z: NDArray,
    size: int,
    ties: tuple[NDArray, ...] | None = None,
) -> NDArray[np.int64]:
    """Index of the lowest point of each bin (-1 for empty bins or flat == -1).

    Ties in z go to the smaller index, one compiled pass (``_min_argmin``); with
    ``ties`` (keys such as x, y) to the smallest first key, then the next, so the
    choice does not depend on the order of the points.
    """
    flat = np.asarray(flat, dtype=np.int64)
    zmin, low = _min_argmin(flat, np.asarray(z, dtype=np.float64), size)
    if ties is None:
        return low
    inbin = flat >= 0
    hit = np.flatnonzero(inbin & (np.asarray(z) == zmin[np.where(inbin, flat, 0)]))
    hit = hit[np.lexsort(tuple(np.asarray(k)[hit] for k in reversed(ties)) + (flat[hit],))]
    f = flat[hit]
    first = np.r_[True, f[1:] != f[:-1]]
    low[f[first]] = hit[first]
    return low


class BinGrid(Protocol):
    """What the per-bin statistics need of a grid: a square ``Grid`` or the
    rings and sectors of a ``ConcentricGrid``."""

    @property
    def size(self) -> int: ...

    @property
    def cell(self) -> float | NDArray[np.float64]: ...

    def index(self, x: NDArray, y: NDArray) -> NDArray[np.int64]: ...

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...


def bin_statistics(
    xyz: NDArray[np.float64], grid: BinGrid, flat: NDArray[np.int64] | None = None
) -> BinStats:
    """Count, min, max, mean, RMS and lowest point of every bin of ``grid``.

    ``flat`` is ``grid.index`` of the points when the caller has it already.
    Two compiled passes over the points (sums, then deviations from the mean).
    """
    if flat is None:
        flat = grid.index(xyz[:, 0], xyz[:, 1])
    flat = np.asarray(flat, dtype=np.int64)
    z = np.asarray(xyz[:, 2], dtype=np.float64)
    n, zsum, zmin, zmax, lowest = _level_sums(flat, z, grid.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        zmean = zsum / n
        rms = np.sqrt(_squared_deviations(flat, z, zmean) / n)
    empty = n == 0
    zmin[empty] = np.nan
    zmax[empty] = np.nan
    return BinStats(grid, n, zmin, zmax, zmean, rms, lowest)


@dataclass(frozen=True)
class PlaneStats:
    """Least-squares plane z = c + sx·(x − xc) + sy·(y − yc) per bin (NIST §5.2, §7).

    ``xc, yc`` are bin centres. Bins with fewer than 3 points or a degenerate
    layout get NaN coefficients. ``rms`` and ``lowest`` are judged on the
    residuals about the plane, so a steep but smooth bin has a small RMS.
    """

    grid: BinGrid
    n: NDArray[np.int64]
    c: NDArray[np.float64]
    sx: NDArray[np.float64]
    sy: NDArray[np.float64]
    rms: NDArray[np.float64]
    lowest: NDArray[np.int64]  # index of the point with the most negative residual


def planes_from_sums(
    nf: NDArray[np.float64],
    sums: NDArray[np.float64],
    cell: float | NDArray[np.float64],
    min_n: int,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares planes z = c + sx u + sy v from their point counts ``nf`` and the
    sums (u, v, z, uu, vv, uv, uz, vz) stacked in ``sums``: whether each is solved (at
    least ``min_n`` points, the system not singular at the scale of ``cell``) and c, sx,
    sy (NaN where not). Closed form (the symmetric adjugate), vectorised over planes."""
    su, sv, sz, suu, svv, suv, suz, svz = sums
    a00 = suu * svv - suv * suv
    a01 = sv * suv - su * svv
    a02 = su * suv - suu * sv
    a11 = nf * svv - sv * sv
    a12 = su * sv - nf * suv
    a22 = nf * suu - su * su
    det = nf * a00 + su * a01 + sv * a02
    ok = (nf >= min_n) & (np.abs(det) > 1e-9 * np.maximum(1.0, nf) * cell**4)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(ok, 1.0 / det, np.nan)
    c = (a00 * sz + a01 * suz + a02 * svz) * inv
    sx = (a01 * sz + a11 * suz + a12 * svz) * inv
    sy = (a02 * sz + a12 * suz + a22 * svz) * inv
    return ok, c, sx, sy


def plane_fit_statistics(
    xyz: NDArray[np.float64], grid: BinGrid, flat: NDArray[np.int64] | None = None
) -> PlaneStats:
    """Fit a least-squares plane in every bin at once via per-bin normal equations.

    The sums are one compiled pass over the points; the 3 × 3 systems are
    solved in closed form (cofactors), vectorised over bins: a batched LAPACK
    solve costs more than all the sums. A second pass gives the residuals.
    ``flat`` is ``grid.index`` of the points when the caller has it already.
    """
    if flat is None:
        flat = grid.index(xyz[:, 0], xyz[:, 1])
    flat = np.asarray(flat, dtype=np.int64)
    x, y, z = (np.asarray(xyz[:, k], dtype=np.float64) for k in range(3))
    cx, cy = grid.centers()
    n, sums = _plane_sums(flat, x, y, z, cx, cy)
    ok, c, sx, sy = planes_from_sums(n.astype(np.float64), sums.T, grid.cell, min_n=3)
    # Residuals about zero planes in bins without a fit keep every residual
    # finite; those bins get NaN / -1 below.
    c0, sx0, sy0 = (np.where(ok, a, 0.0) for a in (c, sx, sy))
    ss, _, lowest = _plane_residuals(flat, x, y, z, cx, cy, c0, sx0, sy0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(ss / n)
    rms[~ok] = np.nan
    lowest[~ok] = -1
    return PlaneStats(grid, n, c, sx, sy, rms, lowest)
