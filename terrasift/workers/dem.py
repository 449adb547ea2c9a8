"""Elevation models on a block's window of the job raster.

DTM: the TIN through one vertex per cell of ground (the centroid of the
cell's lowest ground points, so an overhang's roof, also labelled ground,
never lifts the 2.5-D terrain), sampled at cell centres. DSM: the highest point per cell, small holes filled from the nearest
filled cell. Cells farther than ``reach`` from any point are nodata (NaN):
the models do not invent terrain outside the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from terrasift.workers.bins import Grid, lowest_per_bin
from terrasift.workers.surface import TinSurface


@dataclass(frozen=True)
class Window:
    """A north-up raster window: upper-left corner, cell size, shape."""

    xmin: float
    ymax: float
    resolution: float
    rows: int
    cols: int

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        xs = self.xmin + (np.arange(self.cols) + 0.5) * self.resolution
        ys = self.ymax - (np.arange(self.rows) + 0.5) * self.resolution
        return np.meshgrid(xs, ys)

    def cell_of(
        self, x: NDArray, y: NDArray
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
        """Row, column and inside-flag of each point."""
        col = np.floor((x - self.xmin) / self.resolution).astype(np.int64)
        row = np.floor((self.ymax - y) / self.resolution).astype(np.int64)
        inside = (col >= 0) & (col < self.cols) & (row >= 0) & (row < self.rows)
        return row, col, inside

    def grown(self, margin: float) -> Window:
        """This window grown by ``margin`` metres (rounded up to whole cells) on every side."""
        k = int(np.ceil(margin / self.resolution))
        r = self.resolution
        return Window(self.xmin - k * r, self.ymax + k * r, r, self.rows + 2 * k, self.cols + 2 * k)


def lowest_per_cell(xyz: NDArray[np.float64], resolution: float) -> NDArray[np.float64]:
    """The lowest point of each occupied ``resolution`` cell."""
    if xyz.shape[0] == 0:
        return xyz
    grid = Grid.covering(xyz[:, 0], xyz[:, 1], resolution)
    idx = lowest_per_bin(grid.index(xyz[:, 0], xyz[:, 1]), xyz[:, 2], grid.size)
    return xyz[idx[idx >= 0]]


def data_reach_mask(xyz: NDArray[np.float64], window: Window, reach: float) -> NDArray[np.bool_]:
    """True for cells within ``reach`` metres of some point (any class)."""
    margin = window.grown(reach)
    row, col, inside = margin.cell_of(xyz[:, 0], xyz[:, 1])
    occupied = np.zeros((margin.rows, margin.cols), dtype=bool)
    occupied[row[inside], col[inside]] = True
    if not occupied.any():
        return np.zeros((window.rows, window.cols), dtype=bool)
    dist = ndimage.distance_transform_edt(~occupied) * window.resolution
    k = (margin.rows - window.rows) // 2
    return dist[k : k + window.rows, k : k + window.cols] <= reach


def ground_vertices(
    ground_xyz: NDArray[np.float64], cell: float, band: float = 0.5
) -> NDArray[np.float64]:
    """One TIN vertex per occupied ``cell``: the centroid of the cell's ground
    points within ``band`` of its lowest one.

    The centroid lies on a plane through its points, so planar ground is kept
    exactly while noise averages out (a lowest point would sit low by about
    one noise sigma); the band keeps an overhang's roof out of the 2.5-D
    surface. Decimating to one vertex per cell makes the Delaunay cheap.
    """
    if ground_xyz.shape[0] == 0:
        return ground_xyz
    grid = Grid.covering(ground_xyz[:, 0], ground_xyz[:, 1], cell)
    flat = grid.index(ground_xyz[:, 0], ground_xyz[:, 1])
    low = lowest_per_bin(flat, ground_xyz[:, 2], grid.size)
    zmin = np.where(low >= 0, ground_xyz[np.maximum(low, 0), 2], np.inf)
    near = ground_xyz[:, 2] - zmin[flat] <= band
    f = flat[near]
    n = np.bincount(f, minlength=grid.size)
    occ = n > 0
    local = ground_xyz[near] - (grid.x0, grid.y0, 0.0)
    cen = [np.bincount(f, weights=local[:, i], minlength=grid.size)[occ] / n[occ] for i in range(3)]
    return np.column_stack(cen) + (grid.x0, grid.y0, 0.0)


def ground_tin(ground_xyz: NDArray[np.float64], cell: float = 1.0) -> TinSurface | None:
    """The block's ground surface: a TIN through ``ground_vertices`` on ``cell``
    cells (None without ground). One TIN serves the DTM and heights above ground."""
    if ground_xyz.shape[0] == 0:
        return None
    return TinSurface(ground_vertices(ground_xyz, cell))


def sample_window(surface: TinSurface | None, window: Window) -> NDArray[np.float32]:
    """``surface`` at the window's cell centres (NaN everywhere without a surface)."""
    if surface is None:
        return np.full((window.rows, window.cols), np.nan, np.float32)
    gx, gy = window.centers()
    return surface(gx, gy).astype(np.float32)


def dsm_window(xyz: NDArray[np.float64], window: Window) -> NDArray[np.float32]:
    """Highest point per cell; empty cells take the nearest filled cell's value."""
    row, col, inside = window.cell_of(xyz[:, 0], xyz[:, 1])
    out: NDArray = np.full(window.rows * window.cols, -np.inf)
    flat = row[inside] * window.cols + col[inside]
    np.maximum.at(out, flat, xyz[inside, 2]) if flat.size < 4096 else _max_sorted(
        out, flat, xyz[inside, 2]
    )
    out = out.reshape(window.rows, window.cols)
    empty = ~np.isfinite(out)
    if empty.all():
        return np.full(out.shape, np.nan, np.float32)
    if empty.any():
        _, (ri, ci) = ndimage.distance_transform_edt(empty, return_indices=True)
        out = out[ri, ci]
    return out.astype(np.float32)


def _max_sorted(out: NDArray, flat: NDArray, values: NDArray) -> None:
    order = np.argsort(flat, kind="stable")
    fs = flat[order]
    starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
    out[fs[starts]] = np.maximum.reduceat(values[order], starts)


def default_reach(density: float, resolution: float) -> float:
    """How far a cell may be from data and still get a value: a few point
    spacings at ``density`` points per m²."""
    spacing = np.sqrt(1.0 / max(density, 1e-9))
    return float(max(2.0 * resolution, 3.0 * spacing, 1.0))
