"""Mixed-measurement removal for ground-based scans (Tuley, Vandapel, Hebert 2005, §IV).

A mixed measurement lands between a foreground edge and the background behind
it, so mixed returns line up along the rays in the edge's range shadow: a thin
sheet that contains the ray. Per interest point (or sparse voxel) we take a box
whose long axis is the ray sensor→point, the point at the centre of its front
face; the scatter matrix of the points in the box gives eigenvalues
λ0 ≥ λ1 ≥ λ2 and the saliencies linear = λ0−λ1, surface = λ1−λ2, random = λ2.
A trigger (surface dominates, or the fitted normal is near orthogonal to the
ray, or both) starts one of six marking variants.

Neighbours are gathered through a sparse hash of sensor-centred angular cells:
points are sorted by (cell, range) and carry prefix sums of their first and
second moments, so the points of one cell inside a range interval — the part of
a cell that lies in a box — cost two binary searches and one subtraction, and
marking an interval is two entries in a difference array. Boxes are therefore
resolved to whole cells across the ray (``cell_angle``) and exactly along it.
No Python loop runs over points; the only loop is over scan positions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from terrasift.errors import InputError, ParameterError
from terrasift.workers.mixed_box import box_frames, window_pairs
from terrasift.workers.registry import StageParams, register

Variant = Literal["naive", "aggressive", "accumulator", "exclusive", "blind_window", "exclusive_blind_window"]
Trigger = Literal["surfaceness", "normal", "both"]


class MixedParams(StageParams):
    """Parameters of the mixed-measurement filter (lengths in metres, angles in degrees)."""

    variant: Variant = "exclusive_blind_window"
    """Marking: naive (the interest point), aggressive (the whole box), accumulator
    (points reported by at least ``votes`` boxes), exclusive (box but the interest
    point), blind_window (box but a slab of ``blind_depth`` behind the interest
    point), exclusive_blind_window (blind window and not the interest point)."""
    trigger: Trigger = "normal"
    """surfaceness: surface saliency dominates the box; normal: the fitted plane
    contains the ray within ``normal_angle``; both: the two together."""
    votes: int = Field(3, ge=1, le=1000)
    """Votes a point needs to be marked by the accumulator variant."""
    box_width: float = Field(0.15, gt=0.0, le=10.0)
    """Box extent across the ray, horizontal before roll."""
    box_height: float = Field(0.5, gt=0.0, le=10.0)
    """Box extent across the ray, vertical before roll."""
    box_depth: float = Field(2.5, gt=0.0, le=20.0)
    """Box extent along the ray behind the interest point (the seed saw mixing up to 2.5 m)."""
    box_roll: float = Field(0.0, ge=-90.0, le=90.0)
    """Rotation of the box about the ray, to find mixed sheets in non-vertical planes."""
    blind_depth: float = Field(0.15, ge=0.0, le=10.0)
    """Depth behind the interest point left unmarked by the blind-window variants."""
    normal_angle: float = Field(5.0, gt=0.0, le=90.0)
    """Largest deviation of the plane normal from orthogonal to the ray (normal trigger)."""
    surface_ratio: float = Field(1.0, ge=0.1, le=100.0)
    """surfaceness fires when surface > surface_ratio × max(linear, random)."""
    thinness: float = Field(0.6, gt=0.0, le=1.0)
    """The fitted sheet must be thinner (rms across it) than thinness × box_width / √12,
    the rms of points filling the box width; random clutter fills it."""
    voxel_size: float = Field(0.05, ge=0.0, le=1.0)
    """Range step of the sparse voxels that share one interest box (0: one box per point)."""
    cell_angle: float = Field(0.25, gt=0.0, le=5.0)
    """Angular size of the hash cells seen from the sensor; sets the lateral precision."""
    min_points: int = Field(12, ge=3, le=1000)
    """Boxes with fewer points are not classified. Saliency needs three (the seed's
    minimum); 12 keeps sparse random clutter, whose few points always look planar
    in a thin box, from firing (seed §V-D)."""

    @model_validator(mode="after")
    def _check(self) -> MixedParams:
        if self.blind_depth >= self.box_depth:
            raise ValueError("blind_depth must be smaller than box_depth")
        if self.voxel_size >= self.box_depth:
            raise ValueError("voxel_size must be smaller than box_depth")
        return self


@dataclass(frozen=True)
class MixedResult:
    """Marked points, points no box could classify, and counts."""

    marked: NDArray[np.bool_]
    unclassified: NDArray[np.bool_]
    loss_rate: float  # unclassified / all points
    n_points: int
    n_marked: int
    n_unclassified: int
    n_regions: int  # interest boxes evaluated
    n_triggered: int  # interest boxes whose trigger fired


@register("mixed", MixedParams, "Tuley mixed-measurement removal for ground-based scans")
def mark_mixed(
    xyz: NDArray[np.float64],
    params: MixedParams,
    sensor_origin: NDArray[np.float64],
    scan_id: NDArray[np.integer] | None = None,
) -> MixedResult:
    """Mark mixed measurements of one or several scans with known sensor origins.

    ``sensor_origin`` is (3,) for one scan, or (k, 3) with ``scan_id`` giving each
    point's scan position (0..k-1). Coordinates may be absolute: each scan is
    shifted to its own sensor before anything else.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be (n, 3), got {xyz.shape}")
    origins, ids = _scan_layout(xyz.shape[0], sensor_origin, scan_id)
    n = xyz.shape[0]
    marked = np.zeros(n, dtype=bool)
    unclassified = np.zeros(n, dtype=bool)
    n_regions = n_triggered = 0
    for k in range(origins.shape[0]):
        idx = np.flatnonzero(ids == k) if ids is not None else slice(None)
        m, u, nr, nt = _mark_scan(xyz[idx] - origins[k], params)
        marked[idx], unclassified[idx] = m, u
        n_regions += nr
        n_triggered += nt
    n_unc = int(unclassified.sum())
    return MixedResult(
        marked=marked,
        unclassified=unclassified,
        loss_rate=n_unc / n if n else 0.0,
        n_points=n,
        n_marked=int(marked.sum()),
        n_unclassified=n_unc,
        n_regions=n_regions,
        n_triggered=n_triggered,
    )


def _scan_layout(n: int, sensor_origin, scan_id) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
    origins = np.asarray(sensor_origin, dtype=np.float64)
    if origins.shape == (3,):
        origins = origins[None, :]
    if origins.ndim != 2 or origins.shape[1] != 3 or origins.shape[0] == 0:
        raise ParameterError(f"sensor_origin must be (3,) or (k, 3), got {np.shape(sensor_origin)}")
    if not np.isfinite(origins).all():
        raise ParameterError("sensor_origin must be finite")
    if scan_id is None:
        if origins.shape[0] > 1:
            raise ParameterError("several sensor origins need a per-point scan_id")
        return origins, None
    ids = np.asarray(scan_id)
    if ids.shape != (n,) or not np.issubdtype(ids.dtype, np.integer):
        raise ParameterError(f"scan_id must be an integer array of shape ({n},)")
    if n and (ids.min() < 0 or ids.max() >= origins.shape[0]):
        raise ParameterError(f"scan_id values must lie in 0..{origins.shape[0] - 1}")
    return origins, ids.astype(np.intp)


def _mark_scan(rel: NDArray[np.float64], p: MixedParams) -> tuple[NDArray, NDArray, int, int]:
    """Filter one scan; ``rel`` is relative to its sensor. Returns marks, unclassified, counts."""
    n = rel.shape[0]
    marked = np.zeros(n, dtype=bool)
    unclassified = np.ones(n, dtype=bool)
    r = np.linalg.norm(rel, axis=1)
    valid = np.flatnonzero(r > 1e-6)
    if valid.size == 0:
        return marked, unclassified, 0, 0
    q, r = rel[valid], r[valid]

    # Sparse hash of angular cells; points sorted by (cell, range).
    beta = np.radians(p.cell_angle)
    n_az = int(np.ceil(2 * np.pi / beta))
    n_el = int(np.ceil(np.pi / beta)) + 1
    az = np.arctan2(q[:, 1], q[:, 0])
    el = np.arcsin(np.clip(q[:, 2] / r, -1.0, 1.0))
    ia = np.minimum(((az + np.pi) / beta).astype(np.int64), n_az - 1)
    ie = np.minimum(((el + np.pi / 2) / beta).astype(np.int64), n_el - 1)
    cell = ia * n_el + ie
    order = np.lexsort((r, cell))
    q, r, cell, ia, ie = q[order], r[order], cell[order], ia[order], ie[order]
    big = float(2 ** int(np.ceil(np.log2(r.max() + p.box_depth + 2.0))))
    key = cell * big + r
    occupied = np.zeros(n_az * n_el, dtype=bool)
    occupied[cell] = True

    # Interest voxels: runs of one cell within one range step; the nearest point is the interest point.
    rbin = np.floor(r / p.voxel_size).astype(np.int64) if p.voxel_size > 0 else np.arange(r.size)
    new = np.ones(r.size, dtype=bool)
    new[1:] = (cell[1:] != cell[:-1]) | (rbin[1:] != rbin[:-1])
    first = np.flatnonzero(new)
    item_of = np.cumsum(new) - 1
    n_items = first.size
    P, r0 = q[first], r[first]

    frames = box_frames(P, np.radians(p.box_roll))
    it, pc = window_pairs(
        P, r0, ia[first], ie[first], frames, p.box_width, p.box_height, beta, n_az, n_el, occupied
    )
    lo = np.searchsorted(key, pc * big + r0[it], side="left")
    hi = np.searchsorted(key, pc * big + r0[it] + p.box_depth, side="right")
    nz = hi > lo  # most covered cells hold nothing within the box's range interval
    it, pc, lo, hi = it[nz], pc[nz], lo[nz], hi[nz]

    # Box moments from prefix sums, coordinates relative to each interest point's sensor frame.
    mom = np.empty((r.size + 1, 10))
    mom[0] = 0.0
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    np.cumsum(np.column_stack([np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z]), axis=0, out=mom[1:])
    diff = mom[hi] - mom[lo]
    S = np.column_stack([np.bincount(it, weights=diff[:, j], minlength=n_items) for j in range(10)])
    cnt = S[:, 0]
    classified = cnt >= p.min_points
    fired = np.zeros(n_items, dtype=bool)
    ci = np.flatnonzero(classified)
    if ci.size:
        fired[ci] = _trigger(S[ci], frames[ci], p)

    # Marking through a difference array over the sorted points.
    sel = fired[it]
    if p.variant in ("blind_window", "exclusive_blind_window"):
        lo_m = np.searchsorted(key, pc[sel] * big + r0[it[sel]] + p.blind_depth, side="left")
    else:
        lo_m = lo[sel]
    votes = np.bincount(lo_m, minlength=r.size + 1) - np.bincount(hi[sel], minlength=r.size + 1)
    votes = np.cumsum(votes[:-1])
    own = fired[item_of]  # the point's own box fired
    own_in_window = own & (r - r0[item_of] >= (p.blind_depth if "blind" in p.variant else 0.0))
    if p.variant == "naive":
        m = own
    elif p.variant == "aggressive":
        m = votes > 0
    elif p.variant == "accumulator":
        m = votes >= p.votes
    elif p.variant == "exclusive":
        m = (votes - own_in_window) > 0
    elif p.variant == "blind_window":
        m = (votes > 0) | own
    else:  # exclusive_blind_window
        m = (votes - own_in_window) > 0
    unc = ~classified[item_of] & ~m

    back = valid[order]
    marked[back] = m
    unclassified[back] = unc
    return marked, unclassified, n_items, int(fired.sum())


def _trigger(S: NDArray[np.float64], frames: NDArray[np.float64], p: MixedParams) -> NDArray[np.bool_]:
    """Saliency of each box from its moment sums; which boxes fire."""
    n = S[:, 0]
    mean = S[:, 1:4] / n[:, None]
    xx, xy, xz, yy, yz, zz = (S[:, 4 + j] / n for j in range(6))
    cov = np.empty((n.size, 3, 3))
    cov[:, 0, 0] = xx - mean[:, 0] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = xy - mean[:, 0] * mean[:, 1]
    cov[:, 0, 2] = cov[:, 2, 0] = xz - mean[:, 0] * mean[:, 2]
    cov[:, 1, 1] = yy - mean[:, 1] ** 2
    cov[:, 1, 2] = cov[:, 2, 1] = yz - mean[:, 1] * mean[:, 2]
    cov[:, 2, 2] = zz - mean[:, 2] ** 2
    # normal: a thin sheet whose plane contains the ray, i.e. passes through the
    # sensor: the normal is orthogonal to the ray to the box's centroid. The
    # ground, seen from a mast, is a plane that misses the sensor by the mast height.
    w, v = np.linalg.eigh(cov)  # ascending
    lam2, lam1 = np.maximum(w[:, 0], 0.0), w[:, 1]
    thin = lam2 < (p.thinness * p.box_width) ** 2 / 12.0
    mdir = mean / np.linalg.norm(mean, axis=1, keepdims=True)
    cos_nr = np.abs(np.einsum("ij,ij->i", v[:, :, 0], mdir))
    perp = thin & (lam1 > 4.0 * lam2) & (cos_nr <= np.sin(np.radians(p.normal_angle)))
    # surfaceness: saliency in box units (each axis over the box's extent), so a
    # box filled at random is isotropic; the sheet must be the box's long plane
    # (normal along the width axis), which roll turns about the ray.
    scale = np.array([1.0 / p.box_depth, 1.0 / p.box_width, 1.0 / p.box_height])
    R = frames * scale[None, :, None]
    cb = R @ cov @ np.transpose(R, (0, 2, 1))
    wb, vb = np.linalg.eigh(cb)
    b2, b1, b0 = np.maximum(wb[:, 0], 0.0), wb[:, 1], wb[:, 2]
    linear, surface, random = b0 - b1, b1 - b2, b2
    along_u = np.abs(vb[:, 1, 0]) >= np.abs(vb[:, [0, 2], 0]).max(axis=1)
    surf = along_u & (surface > p.surface_ratio * np.maximum(linear, random))
    if p.trigger == "surfaceness":
        return surf
    if p.trigger == "normal":
        return perp
    return surf & perp
