"""Per-bin statistics on a regular grid: the select/reject basis of NIST §2.

Everything is computed with ``np.bincount`` over flat bin indices, so one call
costs a few passes over the points whatever the number of bins. Bins are
addressed row-major from the grid origin (lower-left corner): ``flat = iy * nx + ix``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


#: Local origins of blocks are multiples of this many metres, a common multiple
#: of every usual bin size (0.5 … 240 m), so bins of two blocks line up and a
#: point near a block edge falls in the same bin whichever block it is in.
ANCHOR = 240.0


def anchored_origin(xy: NDArray[np.float64], anchor: float = ANCHOR) -> NDArray[np.float64]:
    """The multiple of ``anchor`` at or below the smallest x and y of ``xy``."""
    xy = np.asarray(xy, dtype=np.float64)
    # Column by column: a reduction over axis 0 of (n, 2) rows is several times slower.
    return np.floor(np.array([xy[:, 0].min(), xy[:, 1].min()]) / anchor) * anchor


def cell_order(x: NDArray[np.float64], y: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Stable permutation putting points in row-major order of the ``cell``-sized
    squares of a grid through the origin.

    The cell key is sorted by numpy's radix sort on 16-bit digits (one pass
    when there are fewer than 65536 cells, two up to 2**32): several times
    faster than a comparison sort of millions of 64-bit keys, same permutation.
    """
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
        x0 = np.floor(x.min() / cell) * cell
        y0 = np.floor(y.min() / cell) * cell
        nx = int(np.floor((x.max() - x0) / cell)) + 1
        ny = int(np.floor((y.max() - y0) / cell)) + 1
        return cls(float(x0), float(y0), float(cell), nx, ny)

    @property
    def size(self) -> int:
        return self.nx * self.ny

    def index(self, x: NDArray, y: NDArray) -> NDArray[np.int64]:
        """Flat bin index of each point, -1 for points outside the grid.

        Truncation equals the floor on the non-negative offsets that can be
        inside, so no separate floor pass over millions of points is needed.
        """
        fx = (np.asarray(x, dtype=np.float64) - self.x0) / self.cell
        fy = (np.asarray(y, dtype=np.float64) - self.y0) / self.cell
        ix = fx.astype(np.int64)
        iy = fy.astype(np.int64)
        if ix.size and fx.min() >= 0 and fy.min() >= 0 and ix.max() < self.nx and iy.max() < self.ny:
            inside = None  # the usual case, settled by four reductions
        else:
            inside = (fx >= 0) & (ix < self.nx) & (fy >= 0) & (iy < self.ny)
        iy *= self.nx
        iy += ix
        if inside is not None:
            iy[~inside] = -1
        return iy

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

    grid: Grid
    n: NDArray[np.int64]
    zmin: NDArray[np.float64]
    zmax: NDArray[np.float64]
    zmean: NDArray[np.float64]
    rms: NDArray[np.float64]
    lowest: NDArray[np.int64]  # index (into the input points) of each bin's lowest point


def lowest_per_bin(flat: NDArray[np.int64], z: NDArray, size: int) -> NDArray[np.int64]:
    """Index of the lowest point of each bin (-1 for empty bins or flat == -1).

    Ties go to the smaller index. Two scatter passes (``ufunc.at`` is fast
    since numpy 1.25) instead of a lexsort, which costs seconds on millions.
    """
    valid = np.flatnonzero(flat >= 0)
    f, zv = flat[valid], z[valid]
    zmin = np.full(size, np.inf)
    np.minimum.at(zmin, f, zv)
    return _lowest_given_min(f, zv, zmin, valid)


def _lowest_given_min(
    f: NDArray[np.int64], z: NDArray, zmin: NDArray, ids: NDArray[np.int64] | None
) -> NDArray[np.int64]:
    """Smallest index among the points of each bin whose ``z`` equals the bin's ``zmin``.

    ``f`` holds valid bins only; ``ids`` maps its rows to point indices (None: identity).
    """
    hit = np.flatnonzero(z == zmin[f])
    big = np.iinfo(np.int64).max
    out = np.full(zmin.size, big, dtype=np.int64)
    np.minimum.at(out, f[hit], hit if ids is None else ids[hit])
    out[out == big] = -1
    return out


def bin_statistics(xyz: NDArray[np.float64], grid: Grid, flat: NDArray[np.int64] | None = None) -> BinStats:
    """Count, min, max, mean, RMS and lowest point of every bin of ``grid``.

    ``flat`` is ``grid.index`` of the points when the caller has it already.
    """
    if flat is None:
        flat = grid.index(xyz[:, 0], xyz[:, 1])
    f, z, ids = _valid(flat, xyz[:, 2])
    size = grid.size
    n = np.bincount(f, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        zsum = np.bincount(f, weights=z, minlength=size)
        zmean = zsum / n
        dev = z - zmean[f]
        rms = np.sqrt(np.bincount(f, weights=dev * dev, minlength=size) / n)
    zmin = np.full(size, np.inf)
    np.minimum.at(zmin, f, z)
    zmax = np.full(size, -np.inf)
    np.maximum.at(zmax, f, z)
    lowest = _lowest_given_min(f, z, zmin, ids)  # before the NaNs go in
    empty = n == 0
    zmin[empty] = np.nan
    zmax[empty] = np.nan
    return BinStats(grid, n, zmin, zmax, zmean, rms, lowest)


def _valid(flat: NDArray[np.int64], z: NDArray) -> tuple[NDArray[np.int64], NDArray, NDArray[np.int64] | None]:
    """Bins, values and point indices of the points inside the grid (no copies when all are)."""
    inside = flat >= 0
    if inside.all():
        return flat, z, None
    ids = np.flatnonzero(inside)
    return flat[ids], z[ids], ids


@dataclass(frozen=True)
class PlaneStats:
    """Least-squares plane z = c + sx·(x − xc) + sy·(y − yc) per bin (NIST §5.2, §7).

    ``xc, yc`` are bin centres. Bins with fewer than 3 points or a degenerate
    layout get NaN coefficients. ``rms`` and ``lowest`` are judged on the
    residuals about the plane, so a steep but smooth bin has a small RMS.
    """

    grid: Grid
    n: NDArray[np.int64]
    c: NDArray[np.float64]
    sx: NDArray[np.float64]
    sy: NDArray[np.float64]
    rms: NDArray[np.float64]
    lowest: NDArray[np.int64]  # index of the point with the most negative residual


def plane_fit_statistics(xyz: NDArray[np.float64], grid: Grid, flat: NDArray[np.int64] | None = None) -> PlaneStats:
    """Fit a least-squares plane in every bin at once via bincount'ed normal equations.

    The 3 × 3 systems are solved in closed form (cofactors), vectorised over
    bins: a batched LAPACK solve costs more than all the sums. ``flat`` is
    ``grid.index`` of the points when the caller has it already.
    """
    if flat is None:
        flat = grid.index(xyz[:, 0], xyz[:, 1])
    f, _, ids = _valid(flat, xyz[:, 2])
    size = grid.size
    cx, cy = grid.centers()
    if ids is None:
        u = xyz[:, 0] - cx[f]
        v = xyz[:, 1] - cy[f]
        z = xyz[:, 2]
    else:
        u = xyz[ids, 0] - cx[f]
        v = xyz[ids, 1] - cy[f]
        z = xyz[ids, 2]

    def s(w: NDArray | None) -> NDArray:
        return np.bincount(f, weights=w, minlength=size).astype(np.float64)

    n = np.bincount(f, minlength=size)
    nf = n.astype(np.float64)
    su, sv, sz = s(u), s(v), s(z)
    suu, svv, suv = s(u * u), s(v * v), s(u * v)
    suz, svz = s(u * z), s(v * z)
    # Solve [[n, su, sv], [su, suu, suv], [sv, suv, svv]] @ [c, sx, sy] = [sz, suz, svz]
    # with the (symmetric) adjugate.
    a00 = suu * svv - suv * suv
    a01 = sv * suv - su * svv
    a02 = su * suv - suu * sv
    a11 = nf * svv - sv * sv
    a12 = su * sv - nf * suv
    a22 = nf * suu - su * su
    det = nf * a00 + su * a01 + sv * a02
    ok = (n >= 3) & (np.abs(det) > 1e-9 * np.maximum(1.0, nf) * grid.cell**4)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(ok, 1.0 / det, np.nan)
    c = (a00 * sz + a01 * suz + a02 * svz) * inv
    sx = (a01 * sz + a11 * suz + a12 * svz) * inv
    sy = (a02 * sz + a12 * suz + a22 * svz) * inv
    # Residuals about zero planes in bins without a fit keep every residual
    # finite (no masking passes over the points); those bins get NaN / -1 below.
    c0, sx0, sy0 = (np.where(ok, a, 0.0) for a in (c, sx, sy))
    resid = z - c0[f]
    resid -= sx0[f] * u
    resid -= sy0[f] * v
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.bincount(f, weights=resid * resid, minlength=size) / n)
    rms[~ok] = np.nan
    rmin = np.full(size, np.inf)
    np.minimum.at(rmin, f, resid)
    lowest = _lowest_given_min(f, resid, rmin, ids)
    lowest[~ok] = -1
    return PlaneStats(grid, n, c, sx, sy, rms, lowest)

