"""Concentric grid around a ground-based scanner (NIST §7).

Scan density falls with the square of the range, so equal square bins are
far too fine near the instrument and too coarse far from it. The concentric
grid uses rings of sectors that are all nearly square: a sector's two
diagonals are perpendicular. With angular step Δ, inner radius r1 and outer
radius r2 the diagonals are perpendicular when 2·r1·r2 = (r1² + r2²)·cos Δ,
whose root gives the ring ratio q = r2 / r1 = (1 + sin Δ) / cos Δ. The grid is
fixed by the inner radius, the outer radius and Δ; the outermost ring is
extended to the outer radius so no residual thin ring remains. Points inside
the inner radius share one central bin.

``ConcentricGrid`` has the interface of ``terrasift.workers.bins.Grid`` that
``bin_statistics`` and ``plane_fit_statistics`` use (``index``, ``size``,
``centers``, ``cell``), so both work on it unchanged; ``cell`` is an array
of per-bin sizes there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


def ring_ratio(step: float) -> float:
    """q = (1 + sin Δ) / cos Δ for angular step Δ in radians."""
    return (1.0 + np.sin(step)) / np.cos(step)


@dataclass(frozen=True)
class ConcentricGrid:
    """Rings of sectors around ``(cx, cy)`` from ``r_inner`` to ``r_outer``."""

    cx: float
    cy: float
    r_inner: float
    r_outer: float
    n_sectors: int
    radii: NDArray[np.float64] = field(
        repr=False
    )  # ring boundaries, radii[0] = r_inner, radii[-1] = r_outer

    @classmethod
    def build(
        cls, cx: float, cy: float, r_inner: float, r_outer: float, step_deg: float
    ) -> ConcentricGrid:
        """Grid with sectors of about ``step_deg`` degrees (rounded so they tile the circle)."""
        if not (0 < r_inner < r_outer):
            raise ValueError("need 0 < r_inner < r_outer")
        n_sectors = max(3, int(round(360.0 / step_deg)))
        step = 2 * np.pi / n_sectors
        q = ring_ratio(step)
        n_rings = max(1, int(np.floor(np.log(r_outer / r_inner) / np.log(q))))
        radii = r_inner * q ** np.arange(n_rings + 1, dtype=np.float64)
        radii[-1] = r_outer  # the outermost ring is extended to the outer radius
        return cls(float(cx), float(cy), float(r_inner), float(r_outer), n_sectors, radii)

    @property
    def step(self) -> float:
        return 2 * np.pi / self.n_sectors

    @property
    def n_rings(self) -> int:
        return self.radii.size - 1

    @property
    def size(self) -> int:
        return 1 + self.n_rings * self.n_sectors

    def index(self, x: NDArray, y: NDArray) -> NDArray[np.int64]:
        """Flat bin index: 0 for the central disc, 1 + ring·n_sectors + sector
        for the rings, -1 beyond ``r_outer``."""
        dx = np.asarray(x, dtype=np.float64) - self.cx
        dy = np.asarray(y, dtype=np.float64) - self.cy
        r = np.hypot(dx, dy)
        theta = np.mod(np.arctan2(dy, dx), 2 * np.pi)
        sector = np.minimum((theta / self.step).astype(np.int64), self.n_sectors - 1)
        ring = np.searchsorted(self.radii, r, side="right") - 1
        ring = np.minimum(ring, self.n_rings - 1)
        flat = 1 + ring * self.n_sectors + sector
        flat = np.where(r < self.r_inner, 0, flat)
        return np.where(r <= self.r_outer, flat, -1)

    def centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Bin centres (geometric-mean radius, mid angle); the disc's is the sensor."""
        rc = np.sqrt(self.radii[:-1] * self.radii[1:])
        ang = (np.arange(self.n_sectors) + 0.5) * self.step
        r, a = np.meshgrid(rc, ang, indexing="ij")
        x = np.r_[self.cx, (self.cx + r * np.cos(a)).ravel()]
        y = np.r_[self.cy, (self.cy + r * np.sin(a)).ravel()]
        return x, y

    @property
    def cell(self) -> NDArray[np.float64]:
        """Approximate side length of each bin (radial width)."""
        width = np.repeat(np.diff(self.radii), self.n_sectors)
        return np.r_[2 * self.r_inner, width]
