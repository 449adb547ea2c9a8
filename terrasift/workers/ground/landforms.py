"""Steep-sided landforms that a ground filter took for buildings, given back.

Ground filters remove compact raised bodies: screening deletes a coarse-bin
vertex that stands far above the median of its neighbours, and mowing then
drops everything on it. That is how they remove buildings, and also how they
lose mesas, buttes and small steep hills 15–60 m across.

The rule that tells them apart: **terrain reaches its surroundings through
steep ground, a building through a wall onto level ground.** Around a hill
the flanks keep rising toward it; around a mesa or butte the talus apron
rises to the foot of its faces; around a building the ground is level (on
a regional slope it rises on the uphill side and falls on the downhill side
by the same amount).

Steps, on a raster of the lowest point per ``cell`` (metres; 0: ``spacings``
mean point spacings, at least 1 m):

1. heights above the ground labels' surface (a TIN of their lowest point per
   cell); cells ``min_height`` or more above it are raised;
2. raised cells joined 8-wise are bodies; a body must be opaque and smooth
   like a rock top or a roof — its lowest points differ from the median of
   their neighbours by less than ``rough`` (median over the body) — which tree crowns,
   whose lowest returns jump between crown and ground, are not;
3. the ring of cells within ``ring`` metres outside the body is cut into
   ``sectors`` compass sectors; in each, the rise toward the body is the
   median height of the ring's inner half minus that of its outer half over
   the distance between them. At least ``flank_share`` of the sectors with
   data must rise at ``flank_deg`` or more: all around a hill, mesa or butte,
   only on the downhill side of a building on a slope, nowhere around one
   on level ground.

A body that passes is ground, with its ring (the flanks and talus leading up
to it, which the filter cut with it): the points within ``tol`` of their
cell's lowest point (widened by the slope across the cell), and in the cells
along the body's edge the points of the face (between that cell's lowest
point and the body's top next to it). A mesa with a vertical face straight onto level
ground and no talus has a building's border and is removed like one.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy import ndimage

from terrasift.workers.bins import Grid, lowest_per_bin
from terrasift.workers.registry import StageParams, register


class LandformParams(StageParams):
    """Parameters of the steep-landform rule (lengths in metres)."""

    enabled: bool = True
    """Run the rule after the ground stage (false: the filter's labels as they are)."""
    cell: float = Field(0.0, ge=0.0, le=20.0)
    """Raster cell (0: ``spacings`` mean point spacings, at least 1 m)."""
    spacings: float = Field(2.0, gt=0.0, le=20.0)
    """Mean point spacings per cell when ``cell`` is 0. At 2 pulses/m² cells of
    1.5 spacings hold two points: under a crown at the foot of a face the
    lowest is often a crown return, and the crown joined the body."""
    view_spacings: float = Field(1.5, gt=0.0, le=20.0)
    """``spacings`` in the rotated runs' views (``steps._ground``): their spacing
    comes from the view's bounding box, wider than the points' own, so their
    cells are wider already; 2 there lost faces on the tune band tile."""
    min_height: float = Field(2.0, gt=0.0, le=100.0)
    """A cell is raised when its lowest point stands this high over the ground surface."""
    min_area: float = Field(30.0, ge=0.0, le=1e6)
    """m²: smaller bodies are left alone (boulders, bushes)."""
    rough: float = Field(0.5, gt=0.0, le=10.0)
    """Median |lowest point − median of its 3 × 3 neighbours| above which a body is vegetation."""
    ring: float = Field(4.0, gt=0.0, le=50.0)
    """Width of the ring outside a body whose rise toward it is measured."""
    flank_deg: float = Field(5.0, gt=0.0, lt=90.0)
    """Mean rise of the ring toward the body (degrees) that makes it terrain."""
    sectors: int = Field(8, ge=1, le=64)
    """Compass sectors of the ring, judged each on its own."""
    flank_share: float = Field(0.75, gt=0.0, le=1.0)
    """Share of the sectors (with data) that must rise at ``flank_deg``."""
    min_sectors: int = Field(6, ge=1, le=64)
    """A body must have ring data in this many sectors: free-standing, not hemmed in
    by other raised cells or cut off by the data's edge."""
    tol: float = Field(0.5, gt=0.0, le=10.0)
    """Points this close above their cell's lowest point (in a terrain body) are ground."""


def _cell_size(xyz: NDArray[np.float64], params: LandformParams) -> float:
    if params.cell > 0:
        return params.cell
    span = np.ptp(xyz[:, :2], axis=0)
    area = max(float(span[0] * span[1]), 1.0)
    spacing = np.sqrt(area / max(xyz.shape[0], 1))
    return max(params.spacings * spacing, 1.0)


@register(
    "ground.landforms",
    LandformParams,
    "mesas, buttes and steep hills a filter removed, given back when steep ground leads up to them",
)
def restore_landforms(
    xyz: NDArray[np.float64],
    ground: NDArray[np.bool_],
    params: LandformParams,
    last_return: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """``ground`` plus the points of raised bodies that pass the landform rule
    (module doc); with ``last_return`` (per point: last or only return of its
    pulse) only such points are given back (a crown lets later returns through,
    rock does not)."""
    ground = np.asarray(ground, dtype=bool)
    if not params.enabled or xyz.shape[0] < 16 or np.count_nonzero(ground) < 3:
        return ground
    found = bodies(xyz, ground, params)
    if found is None or not found["keep"].any():
        return ground
    flat, zlo, filled = found["flat"], found["zlo"], found["filled"]
    labels, n_body, keep = found["labels"], found["keep"].size, found["keep"]
    terrain = np.zeros(n_body + 1, dtype=bool)
    terrain[1:] = keep
    core = terrain[labels]
    # The ring that rose to a kept body is the steep ground leading up to it:
    # its lower flanks and talus, which the filter cut with the body.
    body = core | (terrain[found["owner"]] & (found["dist"] > 0) & (found["dist"] <= params.ring))
    # Faces: body cells on its edge, where a near-vertical face splits the cell.
    edge = core & ~ndimage.binary_erosion(core, structure=np.ones((3, 3)))
    top = ndimage.maximum_filter(np.where(core, filled, -np.inf), size=3)
    # On a steep flank a cell spans height: the tolerance grows with the slope
    # across it (up to 2 cells of rise, 63°), as a ground band does.
    gy, gx = np.gradient(filled, found["cell"])
    rise = np.minimum(np.hypot(gx, gy), 2.0) * found["cell"]
    ok = flat >= 0
    cell_of = np.where(ok, flat, 0)
    b = body.ravel()[cell_of] & ok
    zc = zlo[cell_of]
    on_top = b & (xyz[:, 2] <= zc + params.tol + rise.ravel()[cell_of])
    on_face = b & edge.ravel()[cell_of] & (xyz[:, 2] <= top.ravel()[cell_of] + params.tol)
    back = on_top | on_face
    if last_return is not None:
        back &= np.asarray(last_return, dtype=bool)
    return ground | back


def bodies(
    xyz: NDArray[np.float64], ground: NDArray[np.bool_], params: LandformParams
) -> dict[str, Any] | None:
    """The raised bodies of the block and the figures the rule judges them by:
    ``labels`` (raster of body ids), per body ``area`` (m²), ``rough``,
    ``slope`` (rise toward it per sector, NaN without data), ``centre`` (x, y)
    and ``keep``; None when nothing stands raised."""

    from terrasift.workers.surface import TinSurface

    c = _cell_size(xyz, params)
    lo = xyz[:, :2].min(axis=0)
    grid = Grid.covering(xyz[:, 0] - lo[0], xyz[:, 1] - lo[1], c)
    flat = grid.index(xyz[:, 0] - lo[0], xyz[:, 1] - lo[1])
    low = lowest_per_bin(flat, xyz[:, 2], grid.size)
    zlo = np.full(grid.size, np.nan)
    zlo[low >= 0] = xyz[low[low >= 0], 2]
    glow = lowest_per_bin(flat[ground], xyz[ground, 2], grid.size)
    gi = np.flatnonzero(ground)[glow[glow >= 0]]
    if gi.size < 3:
        return None
    gx, gy = grid.centers()
    g = TinSurface(xyz[gi])(gx + lo[0], gy + lo[1])
    height = (zlo - g).reshape(grid.ny, grid.nx)
    z = zlo.reshape(grid.ny, grid.nx)
    raised = np.nan_to_num(height, nan=-np.inf) >= params.min_height
    if not raised.any():
        return None
    labels, n_body = ndimage.label(raised, structure=np.ones((3, 3)))
    # Roughness: |z − median of the 3 × 3 neighbours| over the body's cells.
    filled = np.where(np.isfinite(z), z, g.reshape(z.shape))
    med = ndimage.median_filter(filled, size=3, mode="nearest")
    dev = np.abs(filled - med)
    # Rise toward each body over its ring: median height of the ring's inner half
    # minus that of its outer half, over the distance between them. The first
    # cell out is left aside (it may hold the foot of a wall or a face).
    dist, (iy, ix) = ndimage.distance_transform_edt(~raised, return_indices=True)
    dist = dist * c
    owner = labels[iy, ix]
    mid = 1.5 * c + 0.5 * params.ring
    inner = (dist > 1.5 * c) & (dist <= mid)
    outer = (dist > mid) & (dist <= 1.5 * c + params.ring)
    idx = np.arange(1, n_body + 1)
    area = ndimage.sum(np.ones_like(dev), labels, idx) * c * c
    rough = np.asarray(ndimage.median(dev, labels, idx), dtype=np.float64)

    # Per body and compass sector of its ring (seen from its centroid): a
    # building on a hillside has ground rising to it only on its downhill side.
    sectors = params.sectors
    cy, cx = (
        np.asarray(v, dtype=np.float64)
        for v in zip(*ndimage.center_of_mass(raised, labels, idx), strict=True)
    )
    yy, xx = np.mgrid[0 : grid.ny, 0 : grid.nx]
    own = np.maximum(owner - 1, 0)
    ang = np.arctan2(yy - cy[own], xx - cx[own])
    sec = np.minimum(((ang + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)
    key = owner * sectors + sec
    keys = np.arange(sectors, (n_body + 1) * sectors)

    # Ring cells next to the data's edge see a truncated ring: left out.
    # (Empty cells between sparse points are no edge: gaps of a few cells are closed first.)
    data = ndimage.binary_fill_holes(
        ndimage.binary_closing(np.isfinite(z), structure=np.ones((3, 3)), iterations=2)
    )
    inside = ndimage.binary_erosion(data, structure=np.ones((3, 3)), iterations=2, border_value=0)

    def ring_median(part: NDArray[np.bool_], v: NDArray[np.float64]) -> NDArray[np.float64]:
        lab = np.where(part & inside, key, 0)
        out = np.full(keys.size, np.nan)
        if lab.any():
            present = np.isin(keys, np.unique(lab[lab > 0]))
            out[present] = ndimage.median(v, lab, keys[present])
        return out.reshape(n_body, sectors)

    rise_z = ring_median(inner, filled) - ring_median(outer, filled)
    run = ring_median(outer, dist) - ring_median(inner, dist)
    with np.errstate(invalid="ignore", divide="ignore"):
        # A sector whose halves lie side by side rather than one beyond the other
        # (a sliver of ring at the data's edge) says nothing.
        slope = np.where(run >= 0.25 * params.ring, rise_z / run, np.nan)
    seen = np.isfinite(slope)
    up = np.count_nonzero(seen & (slope >= np.tan(np.radians(params.flank_deg))), axis=1)
    rising = up >= params.flank_share * np.maximum(np.count_nonzero(seen, axis=1), 1)
    rising &= np.count_nonzero(seen, axis=1) >= params.min_sectors
    keep = (area >= params.min_area) & (rough < params.rough) & rising
    return {
        "cell": c,
        "flat": flat,
        "zlo": zlo,
        "filled": filled,
        "labels": labels,
        "owner": owner,
        "dist": dist,
        "area": area,
        "rough": rough,
        "slope": slope,
        "centre": np.column_stack([lo[0] + (cx + 0.5) * c, lo[1] + (cy + 0.5) * c]),
        "keep": keep,
    }
