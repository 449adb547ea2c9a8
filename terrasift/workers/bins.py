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
    return np.floor(np.asarray(xy, dtype=np.float64)[:, :2].min(axis=0) / anchor) * anchor


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
        """Flat bin index of each point, -1 for points outside the grid."""
        ix = np.floor((x - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((y - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        return np.where(inside, iy * self.nx + ix, -1)

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
    hit = zv == zmin[f]
    big = np.iinfo(np.int64).max
    out = np.full(size, big, dtype=np.int64)
    np.minimum.at(out, f[hit], valid[hit])
    out[out == big] = -1
    return out


def bin_statistics(xyz: NDArray[np.float64], grid: Grid) -> BinStats:
    """Count, min, max, mean, RMS and lowest point of every bin of ``grid``."""
    flat = grid.index(xyz[:, 0], xyz[:, 1])
    keep = flat >= 0
    f, z = flat[keep], xyz[keep, 2]
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
    empty = n == 0
    zmin[empty] = np.nan
    zmax[empty] = np.nan
    lowest = lowest_per_bin(flat, xyz[:, 2], size)
    return BinStats(grid, n, zmin, zmax, zmean, rms, lowest)


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


def plane_fit_statistics(xyz: NDArray[np.float64], grid: Grid) -> PlaneStats:
    """Fit a least-squares plane in every bin at once via bincount'ed normal equations."""
    flat = grid.index(xyz[:, 0], xyz[:, 1])
    keep = np.flatnonzero(flat >= 0)
    f = flat[keep]
    size = grid.size
    cx, cy = grid.centers()
    u = xyz[keep, 0] - cx[f]
    v = xyz[keep, 1] - cy[f]
    z = xyz[keep, 2]

    def s(w: NDArray | None) -> NDArray:
        return np.bincount(f, weights=w, minlength=size).astype(np.float64)

    n = np.bincount(f, minlength=size)
    su, sv, sz = s(u), s(v), s(z)
    suu, svv, suv = s(u * u), s(v * v), s(u * v)
    suz, svz = s(u * z), s(v * z)
    # Solve [[n, su, sv], [su, suu, suv], [sv, suv, svv]] @ [c, sx, sy] = [sz, suz, svz]
    a = np.stack(
        [
            np.stack([n.astype(float), su, sv], -1),
            np.stack([su, suu, suv], -1),
            np.stack([sv, suv, svv], -1),
        ],
        -2,
    )
    b = np.stack([sz, suz, svz], -1)
    det = np.linalg.det(a)
    ok = (n >= 3) & (np.abs(det) > 1e-9 * np.maximum(1.0, n.astype(float)) * grid.cell**4)
    coef = np.full((size, 3), np.nan)
    if ok.any():
        coef[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    c, sx, sy = coef[:, 0], coef[:, 1], coef[:, 2]
    resid = z - (c[f] + sx[f] * u + sy[f] * v)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.bincount(f, weights=np.nan_to_num(resid) ** 2, minlength=size) / n)
    rms[~ok] = np.nan
    resid_full = np.full(xyz.shape[0], np.inf)
    resid_full[keep] = np.where(np.isfinite(resid), resid, np.inf)
    flat_ok = np.where((flat >= 0) & np.isfinite(resid_full), flat, -1)
    lowest = lowest_per_bin(flat_ok, resid_full, size)
    lowest[~ok] = -1
    return PlaneStats(grid, n, c, sx, sy, rms, lowest)
